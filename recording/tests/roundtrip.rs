//! A recording written to memory reads back with every sample at its time, steps with
//! their lateness, the losses in the metadata, and a size limit that counts what it kept
//! out.

use recording::read::Recording;
use recording::{Closing, Item, Options, PortSpec, Recorder, Step};
use serde_json::json;
use std::io::Cursor;

fn ports() -> Vec<PortSpec> {
    vec![
        PortSpec {
            name: "sim0.ai.ch0".into(),
            type_name: "f64".into(),
        },
        PortSpec {
            name: "blink.state".into(),
            type_name: "bool".into(),
        },
    ]
}

#[test]
fn what_is_written_reads_back() {
    let mut out = Cursor::new(Vec::new());
    let options = Options {
        wall_offset_ns: 1_000_000_000_000,
        ..Options::default()
    };
    let mut r = Recorder::new(&mut out, ports(), vec!["blink".into()], options).expect("new");
    for k in 0..100u64 {
        let at_ns = 5_000 + k * 1_000_000;
        r.write(
            &Item::Sample {
                port: 0,
                at_ns,
                value: json!(k as f64 / 10.0),
            },
            at_ns + 10,
        )
        .expect("write");
        r.write(
            &Item::Sample {
                port: 1,
                at_ns,
                value: json!(k % 2 == 0),
            },
            at_ns + 10,
        )
        .expect("write");
    }
    r.write(
        &Item::Sample {
            port: 0,
            at_ns: 1,
            value: json!("NaN"),
        },
        2,
    )
    .expect("write");
    let step = Step {
        scheduled_ns: 100,
        started_ns: 150,
        ended_ns: 400,
    };
    r.write(&Item::Step { activity: 0, step }, 500)
        .expect("write");
    r.write(&Item::Step { activity: 7, step }, 500)
        .expect("an unknown activity is counted");
    let closing = Closing {
        ports_lost: vec![3, 0],
        steps_lost: vec![1],
        ..Closing::default()
    };
    let meta = r.finish(&closing).expect("finish");
    assert_eq!(meta["lost"], "4");
    assert_eq!(meta["unknown"], "1");
    let rec = Recording::parse(out.get_ref()).expect("readable");
    assert_eq!(rec.ports.len(), 2);
    assert_eq!(rec.ports[0].port, "sim0.ai.ch0");
    assert_eq!(rec.ports[0].points.len(), 101);
    assert_eq!(rec.ports[0].points[1], (1_000_000_000_000 + 1_005_000, 0.1));
    assert!(rec.ports[0].points[100].1.is_nan());
    assert_eq!(rec.ports[1].points[3].1, 0.0);
    assert_eq!(
        rec.activities[0].steps[0].started_ns - rec.activities[0].steps[0].scheduled_ns,
        50
    );
    assert_eq!(rec.metadata["lost.sim0.ai.ch0"], "3");
    assert_eq!(rec.metadata["lost_steps.blink"], "1");
    assert_eq!(rec.metadata["messages"], "202");
}

/// `n` samples of 1.5 on port 0, 1 ns apart.
fn fill(r: &mut Recorder<&mut Cursor<Vec<u8>>>, n: u64) {
    for k in 0..n {
        let item = Item::Sample {
            port: 0,
            at_ns: k,
            value: json!(1.5),
        };
        r.write(&item, k).expect("write");
    }
}

#[test]
fn past_the_size_limit_items_are_counted_not_written() {
    let mut out = Cursor::new(Vec::new());
    let options = Options {
        max_bytes: 10_000,
        ..Options::default()
    };
    let mut r = Recorder::new(&mut out, ports(), vec![], options).expect("new");
    fill(&mut r, 1_000);
    let written = r.written();
    let meta = r.finish(&Closing::default()).expect("finish");
    assert!(written > 100 && written < 1_000, "{written}");
    assert_eq!(meta["over_limit"], (1_000 - written).to_string());
    assert!(out.get_ref().len() < 20_000, "{}", out.get_ref().len());
}

#[test]
fn a_recording_cut_short_gives_what_it_holds() {
    let mut out = Cursor::new(Vec::new());
    let options = Options::default();
    let mut r = Recorder::new(&mut out, ports(), vec![], options).expect("new");
    fill(&mut r, 200_000);
    r.finish(&Closing::default()).expect("finish");
    let whole = out.into_inner();
    let cut = &whole[..whole.len() / 2];
    let rec = Recording::parse(cut).expect("the start is MCAP");
    assert!(rec.truncated.is_some(), "{rec:?}");
    let n = rec.ports[0].points.len();
    assert!(n > 10_000 && n < 200_000, "{n}");
    assert!(rec.metadata.is_empty());
    assert!(Recording::parse(b"not mcap at all").is_err());
    let e = Recording::read(std::path::Path::new("/tmp")).expect_err("a folder");
    assert!(e.to_string().contains("not a regular file"), "{e}");
}
