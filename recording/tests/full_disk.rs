//! A recording on a disk that fills up, over a writer that answers `ENOSPC` past a given
//! size: the error names the full disk, the file is cut back to its last complete chunk
//! and completed there (any MCAP reader, the strict one included, reads it whole), what
//! did not reach it is counted; a disk that takes nothing more leaves the file cut at its
//! last complete chunk, read back as "cut after N messages", never as an empty recording.

#![allow(
    clippy::unwrap_used,
    reason = "test code: a failed unwrap is a failed test"
)]

use recording::read::Recording;
use recording::write::CHECKPOINT_NS;
use recording::{Capture, Closing, Item, Options, PortSpec, RecordError, Recorder, Sink};
use serde_json::json;
use std::cell::RefCell;
use std::io::Write;
use std::rc::Rc;

/// A disk of `room` bytes: a write past it stores what fits, the next fails with ENOSPC;
/// cutting frees the space again, as a file system does. With `broken`, every write after
/// the first failure fails (a disk that takes nothing more, or an I/O error). A handle:
/// the test keeps one to look at what the disk holds.
#[derive(Clone)]
struct Disk(Rc<RefCell<State>>);

struct State {
    data: Vec<u8>,
    room: usize,
    broken: bool,
    failed: bool,
}

impl Disk {
    fn new(room: usize, broken: bool) -> Disk {
        Disk(Rc::new(RefCell::new(State {
            data: Vec::new(),
            room,
            broken,
            failed: false,
        })))
    }

    fn bytes(&self) -> Vec<u8> {
        self.0.borrow().data.clone()
    }
}

impl Write for Disk {
    fn write(&mut self, buf: &[u8]) -> std::io::Result<usize> {
        let mut d = self.0.borrow_mut();
        let free = d.room.saturating_sub(d.data.len());
        if free == 0 || (d.broken && d.failed) {
            d.failed = true;
            return Err(std::io::Error::from_raw_os_error(28));
        }
        let n = buf.len().min(free);
        d.data.extend_from_slice(&buf[..n]);
        Ok(n)
    }

    fn flush(&mut self) -> std::io::Result<()> {
        Ok(())
    }
}

impl Sink for Disk {
    fn cut(self, len: u64) -> std::io::Result<Self> {
        self.0.borrow_mut().data.truncate(len as usize);
        Ok(self)
    }
}

fn ports() -> Vec<PortSpec> {
    vec![PortSpec {
        name: "sim0.ai.ch0".into(),
        type_name: "f64".into(),
    }]
}

const MS: u64 = 1_000_000;

/// Offers one sample a millisecond, a batch each 20 ms (a chunk is written each second),
/// until a write fails: the error and the samples offered.
fn record_until_full(capture: &mut Capture<Disk>) -> (RecordError, u64) {
    let mut t = 0;
    loop {
        let batch: Vec<Item> = (0..20)
            .map(|k| Item::Sample {
                port: 0,
                at_ns: t + k * MS,
                value: json!(((t + k * MS) / MS) as f64 * 0.5),
            })
            .collect();
        t += 20 * MS;
        if let Err(e) = capture.offer(batch, t) {
            return (e, t / MS);
        }
        assert!(t < 1_000_000 * MS, "the disk never filled");
    }
}

#[test]
fn a_full_disk_is_named_and_the_file_is_completed_at_its_last_whole_chunk() {
    let disk = Disk::new(64 * 1024, false);
    let rec = Recorder::new(disk.clone(), ports(), vec![], Options::default()).unwrap();
    let mut capture = Capture::new(rec, None);
    let (e, offered) = record_until_full(&mut capture);
    let text = e.to_string();
    assert!(
        text.contains("no space left on device (ENOSPC)") && text.contains("last complete chunk"),
        "{text}"
    );
    assert!(capture.failed());
    let kept = capture.written();
    assert!(kept > 0 && kept < offered, "{kept} of {offered}");
    // More offered after the failure is refused and counted.
    let late = vec![Item::Sample {
        port: 0,
        at_ns: 0,
        value: json!(1.0),
    }];
    assert!(matches!(
        capture.offer(late, u64::MAX / 2),
        Err(RecordError::Stopped { .. })
    ));
    let meta = capture.finish(Closing::default()).unwrap();
    assert_eq!(meta["messages"], kept.to_string());
    let unwritten: u64 = meta["unwritten"].parse().unwrap();
    assert_eq!(kept + unwritten, offered + 1, "{meta:?}");
    assert_eq!(meta["lost"], unwritten.to_string());
    assert!(meta["error"].contains("ENOSPC"), "{meta:?}");

    // Whole: the strict reader (footer and end magic required) reads every kept message.
    let bytes = &disk.bytes();
    assert!(bytes.len() <= 64 * 1024);
    let strict = mcap::MessageStream::new(bytes)
        .unwrap()
        .collect::<Result<Vec<_>, _>>()
        .unwrap();
    assert_eq!(strict.len() as u64, kept);
    // In time order, each sample once, from the first: the chunks kept are the first ones.
    let times: Vec<u64> = strict.iter().map(|m| m.log_time / MS).collect();
    assert_eq!(times, (0..kept).collect::<Vec<_>>());
    let back = Recording::parse(bytes).unwrap();
    assert_eq!(back.truncated, None, "{}", back.condition());
    assert_eq!(back.ports[0].points.len() as u64, kept);
    assert_eq!(back.metadata, meta);
    assert_eq!(back.condition(), format!("{kept} messages"));
}

#[test]
fn a_disk_that_takes_nothing_more_leaves_the_file_readable_to_its_last_whole_chunk() {
    let disk = Disk::new(64 * 1024, true);
    let rec = Recorder::new(disk.clone(), ports(), vec![], Options::default()).unwrap();
    let mut capture = Capture::new(rec, None);
    let (e, _) = record_until_full(&mut capture);
    assert!(e.to_string().contains("ENOSPC"), "{e}");
    let kept = capture.written();
    assert!(kept > 0);
    let e = capture.finish(Closing::default()).unwrap_err();
    assert!(e.to_string().contains("ENOSPC"), "{e}");
    // Cut at the end of the last complete chunk: every kept message, no footer.
    let back = Recording::parse(&disk.bytes()).unwrap();
    assert_eq!(back.ports[0].points.len() as u64, kept);
    assert!(back.metadata.is_empty());
    let said = back.condition();
    assert!(
        said.starts_with(&format!("cut after {kept} messages: ")) && said.contains("footer"),
        "{said}"
    );
}

#[test]
fn a_chunk_reaches_the_disk_each_checkpoint() {
    let disk = Disk::new(usize::MAX, false);
    let mut rec = Recorder::new(disk.clone(), ports(), vec![], Options::default()).unwrap();
    rec.checkpoint(0).unwrap();
    let item = Item::Sample {
        port: 0,
        at_ns: 1,
        value: json!(2.5),
    };
    rec.write(&item, 1).unwrap();
    rec.checkpoint(CHECKPOINT_NS - 1).unwrap();
    let before = Recording::parse(&disk.bytes()).unwrap();
    assert_eq!(before.messages, 0, "not a second yet");
    rec.checkpoint(CHECKPOINT_NS).unwrap();
    let after = Recording::parse(&disk.bytes()).unwrap();
    assert_eq!(after.messages, 1);
    assert!(after.condition().starts_with("cut after 1 messages"));
    rec.finish(&Closing::default()).unwrap();
}

#[test]
fn an_empty_recording_is_told_from_a_cut_one() {
    let mut out = std::io::Cursor::new(Vec::new());
    let rec = Recorder::new(&mut out, ports(), vec![], Options::default()).unwrap();
    rec.finish(&Closing::default()).unwrap();
    let empty = Recording::parse(out.get_ref()).unwrap();
    assert_eq!(empty.truncated, None);
    assert_eq!(
        empty.condition(),
        "no messages: the recording is complete and empty"
    );
    for cut in [0, 3] {
        let r = Recording::parse(&out.get_ref()[..cut]).unwrap();
        assert!(
            r.condition().starts_with("cut after 0 messages: "),
            "{}",
            r.condition()
        );
    }
    // Corrupt: a record's length past the end of the file.
    let mut bad = out.get_ref()[..40].to_vec();
    bad.extend_from_slice(&[0x05, 0xff, 0xff, 0xff, 0xff, 0, 0, 0, 0]);
    let r = Recording::parse(&bad).unwrap();
    assert!(
        r.condition().starts_with("cut after 0 messages: "),
        "{}",
        r.condition()
    );
}
