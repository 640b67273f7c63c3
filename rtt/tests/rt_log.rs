//! The real-time logger: records come out in order with their arguments, through the
//! area's level; levels change while it runs; a full queue drops and counts; unknown
//! names are errors that list what exists; an area nothing holds is gone, and starts
//! afresh when asked for again.

#![allow(
    clippy::unwrap_used,
    reason = "test code: a failed unwrap is a failed test"
)]

use rtt::log::{Area, Arg, Entry, Level, LogError, QUEUE_CAPACITY};
use rtt::rt_log;
use std::sync::Mutex;

/// The queue is the process's: one test at a time takes from it.
static ONE_AT_A_TIME: Mutex<()> = Mutex::new(());

fn taken(area: &str) -> Vec<Entry> {
    let mut got = Vec::new();
    rtt::log::drain(|e| {
        if e.area == area {
            got.push(e)
        }
    });
    got
}

#[test]
fn records_come_out_in_order_through_the_areas_level() {
    let _one = ONE_AT_A_TIME.lock().unwrap();
    let area = Area::named("rt_log_order");
    assert_eq!(area.level(), rtt::log::DEFAULT_LEVEL);
    let before = std::time::SystemTime::now();
    let e = std::io::Error::other("connection refused");
    rt_log!(
        area,
        Warn,
        "unit {} failed {} times: {}",
        3u8,
        5u64,
        Arg::display(&e)
    );
    rt_log!(area, Debug, "not at info: {}", 1u32);
    rt_log!(
        area,
        Error,
        "static {} and text {}",
        "words",
        Arg::text(&String::from("copied"))
    );
    let got = taken("rt_log_order");
    let texts: Vec<(Level, &str)> = got.iter().map(|e| (e.level, e.text.as_str())).collect();
    assert_eq!(
        texts,
        [
            (Level::Warn, "unit 3 failed 5 times: connection refused"),
            (Level::Error, "static words and text copied"),
        ]
    );
    assert!(got.iter().all(|e| e.at >= before), "pushed times");

    assert_eq!(
        rtt::log::set_level("rt_log_order", Level::Debug),
        Ok(Level::Info)
    );
    rt_log!(area, Debug, "now at debug: {}", 1u32);
    rt_log!(area, Trace, "not at trace");
    assert_eq!(
        rtt::log::set_level("rt_log_order", Level::Off),
        Ok(Level::Debug)
    );
    rt_log!(area, Error, "off: nothing");
    let got = taken("rt_log_order");
    assert_eq!(got.len(), 1);
    assert_eq!(got[0].text, "now at debug: 1");
    // The same name is the same area.
    assert_eq!(Area::named("rt_log_order").level(), Level::Off);
    assert!(
        rtt::log::levels().contains(&("rt_log_order".to_string(), Level::Off)),
        "{:?}",
        rtt::log::levels()
    );
}

#[test]
fn a_full_queue_drops_and_counts() {
    let _one = ONE_AT_A_TIME.lock().unwrap();
    let area = Area::named("rt_log_full");
    rtt::log::drain(|_| {});
    let before = rtt::log::stats();
    for i in 0..QUEUE_CAPACITY + 25 {
        rt_log!(area, Info, "record {}", i);
    }
    let after = rtt::log::stats();
    assert_eq!(after.dropped - before.dropped, 25);
    assert_eq!(after.queued, QUEUE_CAPACITY as u64);
    let got = taken("rt_log_full");
    assert_eq!(got.len(), QUEUE_CAPACITY);
    assert_eq!(got[0].text, "record 0");
    assert_eq!(
        got[QUEUE_CAPACITY - 1].text,
        format!("record {}", QUEUE_CAPACITY - 1)
    );
    assert_eq!(
        rtt::log::stats().written - after.written,
        QUEUE_CAPACITY as u64
    );
}

#[test]
fn unknown_names_are_errors_that_list_what_exists() {
    let _one = ONE_AT_A_TIME.lock().unwrap();
    let _known = Area::named("rt_log_known");
    let e = rtt::log::set_level("rt_log_unknown", Level::Debug).unwrap_err();
    assert!(
        matches!(&e, LogError::UnknownArea { known, .. } if known.contains(&"rt_log_known".to_string()))
    );
    assert!(
        e.to_string()
            .starts_with("nothing logs as \"rt_log_unknown\"; what does: "),
        "{e}"
    );
    assert_eq!("WARNING".parse::<Level>(), Ok(Level::Warn));
    assert_eq!("debug".parse::<Level>(), Ok(Level::Debug));
    assert_eq!(
        "loud".parse::<Level>().unwrap_err().to_string(),
        "\"loud\" is not a log level; the levels are off, error, warn, info, debug, trace"
    );
}

#[test]
fn more_arguments_than_a_record_holds_are_said_to_be_left_out() {
    let _one = ONE_AT_A_TIME.lock().unwrap();
    let area = Area::named("rt_log_many");
    rt_log!(
        area,
        Info,
        "{} {} {} {} {} {}",
        1u8,
        2u8,
        3u8,
        4u8,
        5u8,
        6u8
    );
    let got = taken("rt_log_many");
    assert_eq!(got[0].text, "1 2 3 4 {} {} (+2 arguments left out)");
}

#[test]
fn an_area_nothing_holds_is_gone_and_comes_back_at_the_default_level() {
    let area = Area::named("rt_log_gone");
    rtt::log::set_level("rt_log_gone", Level::Debug).unwrap();
    assert!(rtt::log::levels().iter().any(|(n, _)| n == "rt_log_gone"));
    let again = Area::named("rt_log_gone");
    assert_eq!(again.level(), Level::Debug, "one area per name while held");
    drop((area, again));
    assert!(
        !rtt::log::levels().iter().any(|(n, _)| n == "rt_log_gone"),
        "its component removed, its area is not listed"
    );
    match rtt::log::set_level("rt_log_gone", Level::Trace) {
        Err(LogError::UnknownArea { known, .. }) => {
            assert!(!known.iter().any(|n| n == "rt_log_gone"));
        }
        other => panic!("expected an unknown area, got {other:?}"),
    }
    assert!(rtt::log::level("rt_log_gone").is_err());
    let back = Area::named("rt_log_gone");
    assert_eq!(
        back.level(),
        rtt::log::DEFAULT_LEVEL,
        "made again, at the default"
    );
    assert_eq!(
        rtt::log::level("rt_log_gone").unwrap(),
        rtt::log::DEFAULT_LEVEL
    );
}
