//! Each kind of picture, from a recording with known content, as PNG (checked by its size
//! and pixel statistics) and SVG; bad requests are refused with what was wrong.

use plot::{Frame, LiveHistogram, PlotError, Size, Span};
use recording::read::Recording;
use recording::{Closing, Item, Options, PortSpec, Recorder, Step};
use serde_json::json;
use std::io::Cursor;
use testkit::TempDir;
use testkit::picture::png_stats;

/// Two ports (a sine, a square wave) at 1 kHz and two activities for 2 s.
fn recording() -> Recording {
    let ports = vec![
        PortSpec {
            name: "a.sine".into(),
            type_name: "f64".into(),
        },
        PortSpec {
            name: "b.square".into(),
            type_name: "bool".into(),
        },
    ];
    let mut out = Cursor::new(Vec::new());
    let acts = vec!["fast".into(), "slow".into()];
    let mut r = Recorder::new(&mut out, ports, acts, Options::default()).expect("new");
    let ms = 1_000_000u64;
    for k in 0..2_000u64 {
        let t = k * ms;
        let sine = (k as f64 / 100.0).sin();
        r.write(
            &Item::Sample {
                port: 0,
                at_ns: t,
                value: json!(sine),
            },
            t,
        )
        .expect("write");
        r.write(
            &Item::Sample {
                port: 1,
                at_ns: t,
                value: json!(k / 250 % 2 == 0),
            },
            t,
        )
        .expect("write");
        let late = 2_000 + (k * 7919 % 50) * 1_000;
        let step = Step {
            scheduled_ns: t,
            started_ns: t + late,
            ended_ns: t + late + 200_000,
        };
        r.write(&Item::Step { activity: 0, step }, t)
            .expect("write");
        if k % 10 == 0 {
            let step = Step {
                scheduled_ns: t,
                started_ns: t + 9_000,
                ended_ns: t + 3 * ms,
            };
            r.write(&Item::Step { activity: 1, step }, t)
                .expect("write");
        }
    }
    r.finish(&Closing::default()).expect("finish");
    Recording::parse(out.get_ref()).expect("readable")
}

fn frame(path: &std::path::Path) -> Frame<'_> {
    Frame {
        path,
        size: Size {
            width: 800,
            height: 500,
        },
    }
}

fn check_png(path: &std::path::Path) {
    let s = png_stats(path).expect("a PNG");
    assert_eq!((s.width, s.height), (800, 500));
    assert!(s.drawn > 0.02 && s.drawn < 0.9, "{}: {s:?}", path.display());
    assert!(s.colours > 8, "{}: {s:?}", path.display());
}

#[test]
fn every_kind_draws_a_picture_that_is_not_blank() {
    let rec = recording();
    let dir = TempDir::new("plot-kinds");
    let p = |n: &str| dir.path().join(n);
    plot::values(&rec, &[], Span::default(), &frame(&p("values.png"))).expect("values");
    check_png(&p("values.png"));
    let zoom = Span {
        from_s: 0.1,
        span_s: Some(0.05),
    };
    plot::timing(&rec, zoom, &frame(&p("timing.png"))).expect("timing");
    check_png(&p("timing.png"));
    plot::lateness(&rec, &frame(&p("lateness.png"))).expect("lateness");
    check_png(&p("lateness.png"));
    let live = LiveHistogram {
        name: "fast".into(),
        buckets: vec![0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 5, 90, 4, 1],
        max_ns: 9_000,
        p50_ns: 4_096,
        p99_ns: 8_192,
    };
    plot::live_lateness(&[live], &frame(&p("live.png"))).expect("live");
    check_png(&p("live.png"));
    plot::values(
        &rec,
        &["a.sine".into()],
        Span::default(),
        &frame(&p("values.svg")),
    )
    .expect("svg");
    let svg = std::fs::read_to_string(p("values.svg")).expect("svg text");
    assert!(svg.starts_with("<svg") && svg.contains("a.sine") && svg.contains("<polyline"));
}

#[test]
fn bad_requests_say_what_was_wrong() {
    let rec = recording();
    let dir = TempDir::new("plot-bad");
    let p = |n: &str| dir.path().join(n);
    let e = plot::values(&rec, &["x.y".into()], Span::default(), &frame(&p("v.png")));
    assert!(
        matches!(e, Err(PlotError::UnknownPort { ref known, .. }) if known == "a.sine, b.square"),
        "{e:?}"
    );
    let e = plot::values(&rec, &[], Span::default(), &frame(&p("v.jpg")));
    assert!(matches!(e, Err(PlotError::Format(_))), "{e:?}");
    let tiny = Frame {
        path: &p("t.png"),
        size: Size {
            width: 10,
            height: 10,
        },
    };
    assert!(matches!(
        plot::values(&rec, &[], Span::default(), &tiny),
        Err(PlotError::Size(10, 10))
    ));
    std::fs::write(p("exists.png"), b"keep").expect("write");
    let e = plot::lateness(&rec, &frame(&p("exists.png")));
    assert!(matches!(e, Err(PlotError::Exists(_))), "{e:?}");
    assert_eq!(std::fs::read(p("exists.png")).expect("kept"), b"keep");
    // A link is never written through, dangling or not.
    std::os::unix::fs::symlink(p("exists.png"), p("link.png")).expect("link");
    std::os::unix::fs::symlink(p("made.png"), p("dangling.png")).expect("link");
    for link in ["link.png", "dangling.png"] {
        let e = plot::lateness(&rec, &frame(&p(link))).expect_err("a link");
        assert!(e.to_string().contains("is a symbolic link"), "{e}");
    }
    assert_eq!(std::fs::read(p("exists.png")).expect("kept"), b"keep");
    assert!(!p("made.png").exists());
    let empty = Recording::default();
    assert!(matches!(
        plot::timing(&empty, Span::default(), &frame(&p("e.png"))),
        Err(PlotError::Empty(_))
    ));
}

/// A recording of one port with `values`, 1 ms apart.
fn one_port(values: &[f64]) -> Recording {
    let ports = vec![PortSpec {
        name: "a.x".into(),
        type_name: "f64".into(),
    }];
    let mut out = Cursor::new(Vec::new());
    let mut r = Recorder::new(&mut out, ports, vec![], Options::default()).expect("new");
    for (k, v) in values.iter().enumerate() {
        let t = k as u64 * 1_000_000;
        let value = if v.is_finite() {
            json!(v)
        } else {
            json!(v.to_string())
        };
        r.write(
            &Item::Sample {
                port: 0,
                at_ns: t,
                value,
            },
            t,
        )
        .expect("write");
    }
    r.finish(&Closing::default()).expect("finish");
    Recording::parse(out.get_ref()).expect("readable")
}

#[test]
fn odd_values_draw_or_are_refused_never_hang() {
    let dir = TempDir::new("plot-odd");
    let p = |n: &str| dir.path().join(n);
    let draw = |vals: &[f64], name: &str| {
        plot::values(&one_port(vals), &[], Span::default(), &frame(&p(name)))
    };
    draw(&[3.0], "single.png").expect("a single point");
    draw(&[2.5, 2.5, 2.5], "flat.png").expect("equal values");
    draw(&[0.0, 1e300, -1e300], "wide.png").expect("a wide range");
    draw(&[1.0, f64::NAN, f64::INFINITY, 2.0], "gaps.png").expect("NaN and inf left out");
    for (vals, name) in [
        (&[0.0, f64::MAX][..], "max.png"),
        (&[-f64::MAX, f64::MAX][..], "both.png"),
    ] {
        let e = draw(vals, name);
        assert!(
            matches!(e, Err(PlotError::Empty(ref m)) if m.contains("too large")),
            "{e:?}"
        );
        assert!(!p(name).exists());
    }
    let e = draw(&[f64::NAN, f64::NAN], "nan.png");
    assert!(matches!(e, Err(PlotError::Empty(_))), "{e:?}");
    check_png(&p("single.png"));
}

/// A recording that is complete and empty, and one cut before its first message, say so
/// for each kind of picture: "no messages" against "cut after 0 messages: …".
#[test]
fn an_empty_recording_is_told_from_a_cut_one() {
    let dir = TempDir::new("plot-empty");
    let p = |n: &str| dir.path().join(n);
    let mut out = Cursor::new(Vec::new());
    let ports = vec![PortSpec {
        name: "a.x".into(),
        type_name: "f64".into(),
    }];
    let r = Recorder::new(&mut out, ports, vec!["a".into()], Options::default()).expect("new");
    r.finish(&Closing::default()).expect("finish");
    let whole = out.into_inner();
    let empty = Recording::parse(&whole).expect("readable");
    // Cut within its first records: not a word of a message came.
    let cut = Recording::parse(&whole[..whole.len() / 3]).expect("readable");
    for (rec, said) in [
        (
            &empty,
            "nothing to plot: no messages: the recording is complete and empty",
        ),
        (&cut, "nothing to plot: cut after 0 messages: "),
    ] {
        let v = plot::values(rec, &[], Span::default(), &frame(&p("v.png"))).expect_err("empty");
        let t = plot::timing(rec, Span::default(), &frame(&p("t.png"))).expect_err("empty");
        let l = plot::lateness(rec, &frame(&p("l.png"))).expect_err("empty");
        for e in [v, t, l] {
            assert!(e.to_string().starts_with(said), "{e}");
        }
    }
}
