//! The ports' unit tests: policies, fan-in and fan-out, connections made and broken at
//! run time, the word register shared by data connections, two threads.

use super::*;

fn pair<T: Clone + Send + Default + 'static>(policy: ConnPolicy) -> (OutputPort<T>, InputPort<T>) {
    let out = OutputPort::new("out");
    let inp = InputPort::new("in");
    connect(&out, &inp, policy).unwrap();
    (out, inp)
}

fn drain(inp: &mut InputPort<i32>) -> Vec<i32> {
    let mut v = Vec::new();
    let mut x = 0;
    while inp.read(&mut x) == FlowStatus::NewData {
        v.push(x);
    }
    v
}

#[test]
fn data_keeps_the_last_value() {
    let (mut out, mut inp) = pair::<i32>(ConnPolicy::data());
    let mut x = -1;
    assert_eq!(inp.read(&mut x), FlowStatus::NoData);
    assert_eq!(x, -1, "NoData leaves the sample alone");
    for v in 1..=5 {
        out.write(&v);
    }
    assert_eq!((inp.read(&mut x), x), (FlowStatus::NewData, 5));
    assert_eq!((inp.read(&mut x), x), (FlowStatus::OldData, 5));
    assert_eq!(
        out.connections()[0].dropped,
        0,
        "data connections overwrite, they do not drop"
    );
}

#[test]
fn buffer_drops_newest_and_counts() {
    let (mut out, mut inp) = pair::<i32>(ConnPolicy::buffer(3));
    for v in 1..=5 {
        out.write(&v);
    }
    assert_eq!(drain(&mut inp), vec![1, 2, 3]);
    let info = &inp.connections()[0];
    assert_eq!((info.written, info.read, info.dropped), (3, 3, 2));
}

#[test]
fn circular_buffer_drops_oldest_and_counts() {
    let (mut out, mut inp) = pair::<i32>(ConnPolicy::circular_buffer(3));
    for v in 1..=5 {
        out.write(&v);
    }
    assert_eq!(drain(&mut inp), vec![3, 4, 5]);
    assert_eq!(out.connections()[0].dropped, 2);
    out.write(&6);
    assert_eq!(drain(&mut inp), vec![6]);
}

#[test]
fn init_hands_a_new_reader_the_last_value() {
    let mut out = OutputPort::<i32>::new("out");
    out.write(&41);
    out.write(&42);
    let mut late = InputPort::new("late");
    connect(&out, &late, ConnPolicy::data().with_init(true)).unwrap();
    let mut x = 0;
    assert_eq!((late.read(&mut x), x), (FlowStatus::NewData, 42));
    let mut plain = InputPort::new("plain");
    connect(&out, &plain, ConnPolicy::buffer(4)).unwrap();
    assert_eq!(
        plain.read(&mut x),
        FlowStatus::NoData,
        "without init a new reader has nothing"
    );
    let mut buffered = InputPort::new("buffered");
    connect(&out, &buffered, ConnPolicy::buffer(4).with_init(true)).unwrap();
    assert_eq!(drain(&mut buffered), vec![42]);
}

#[test]
fn data_connections_of_one_word_share_the_ports_register() {
    let mut out = OutputPort::<f64>::new("out");
    out.write(&1.0);
    let mut plain = InputPort::<f64>::new("plain");
    let mut init = InputPort::<f64>::new("init");
    connect(&out, &plain, ConnPolicy::data()).unwrap();
    connect(&out, &init, ConnPolicy::data().with_init(true)).unwrap();
    let mut x = 0.0;
    assert_eq!(plain.read(&mut x), FlowStatus::NoData, "written before it");
    assert_eq!((init.read(&mut x), x), (FlowStatus::NewData, 1.0));
    for v in [2.0, 3.0] {
        out.write(&v);
    }
    assert_eq!(out.conns.len(), 2);
    assert!(!out.push, "nothing to do per write for register readers");
    for inp in [&mut plain, &mut init] {
        assert_eq!((inp.read(&mut x), x), (FlowStatus::NewData, 3.0));
        assert_eq!((inp.read(&mut x), x), (FlowStatus::OldData, 3.0));
    }
    let counts: Vec<(u64, u64)> = out
        .connections()
        .iter()
        .map(|c| (c.written, c.read))
        .collect();
    assert_eq!(
        counts,
        vec![(2, 1), (3, 2)],
        "written since connected, + init"
    );
    assert_eq!(out.last_written(), Some(3.0));
    // A buffer beside them gets every write; the register readers the latest.
    let mut buffered = InputPort::<f64>::new("buffered");
    connect(&out, &buffered, ConnPolicy::buffer(4)).unwrap();
    out.write(&4.0);
    out.write(&5.0);
    assert!(out.push);
    let mut got = Vec::new();
    while buffered.read(&mut x) == FlowStatus::NewData {
        got.push(x);
    }
    assert_eq!(got, vec![4.0, 5.0]);
    assert_eq!((plain.read(&mut x), x), (FlowStatus::NewData, 5.0));
    drop(buffered);
    out.write(&6.0);
    assert!(!out.push, "the buffer's end let go");
    assert_eq!(init.disconnect(None), 1);
    out.write(&7.0);
    assert_eq!((init.read(&mut x), x), (FlowStatus::OldData, 3.0));
    assert_eq!((plain.read(&mut x), x), (FlowStatus::NewData, 7.0));
    drop(out);
    assert_eq!(plain.read(&mut x), FlowStatus::OldData);
    assert!(plain.conns.is_empty(), "writer gone, all taken: let go");
}

#[test]
fn a_lone_register_connection_is_read_directly_and_handed_back_whole() {
    let mut out = OutputPort::<f64>::new("out");
    let mut inp = InputPort::<f64>::new("in");
    connect(&out, &inp, ConnPolicy::data()).unwrap();
    let mut x = 0.0;
    assert_eq!(inp.read(&mut x), FlowStatus::NoData);
    assert!(
        inp.direct.is_some(),
        "one register connection: read directly"
    );
    out.write(&1.0);
    assert_eq!((inp.read(&mut x), x), (FlowStatus::NewData, 1.0));
    assert_eq!((inp.read(&mut x), x), (FlowStatus::OldData, 1.0));
    assert_eq!(inp.shared().last_read(), Some(1.0));
    // A second connection: the first's end takes its version back, so the value
    // already read is not new again.
    let mut other = OutputPort::<f64>::new("other");
    connect(&other, &inp, ConnPolicy::data()).unwrap();
    assert_eq!((inp.read(&mut x), x), (FlowStatus::OldData, 1.0));
    assert!(inp.direct.is_none(), "two connections: walked");
    other.write(&10.0);
    out.write(&2.0);
    let mut got = Vec::new();
    while inp.read(&mut x) == FlowStatus::NewData {
        got.push(x);
    }
    got.sort_by(f64::total_cmp);
    assert_eq!(got, vec![2.0, 10.0]);
    // Back to one: direct again, from the version the walk took.
    drop(other);
    assert_eq!((inp.read(&mut x), x), (FlowStatus::OldData, got[1]));
    assert!(inp.direct.is_some());
    assert_eq!(inp.read(&mut x), FlowStatus::OldData, "2.0 was taken");
    out.write(&3.0);
    assert_eq!((inp.read(&mut x), x), (FlowStatus::NewData, 3.0));
    let counts: Vec<(u64, u64)> = inp
        .connections()
        .iter()
        .map(|c| (c.written, c.read))
        .collect();
    assert_eq!(counts, vec![(3, 3)], "every read counted, direct or walked");
    assert_eq!(inp.shared().last_read(), Some(3.0));
    // The writer gone, what it left taken: the reader lets go.
    out.write(&4.0);
    drop(out);
    assert_eq!((inp.read(&mut x), x), (FlowStatus::NewData, 4.0));
    assert_eq!((inp.read(&mut x), x), (FlowStatus::OldData, 4.0));
    assert!(inp.conns.is_empty() && inp.direct.is_none());
}

#[test]
fn a_reader_lets_go_once_it_took_what_a_gone_writer_left() {
    for policy in [ConnPolicy::data(), ConnPolicy::buffer(4)] {
        let (mut out, mut inp) = pair::<f64>(policy);
        out.write(&1.0);
        out.write(&2.0);
        drop(out);
        let mut x = 0.0;
        assert_eq!(inp.read(&mut x), FlowStatus::NewData, "{policy:?}");
        while inp.read(&mut x) == FlowStatus::NewData {}
        assert_eq!((inp.read(&mut x), x), (FlowStatus::OldData, 2.0));
        assert!(
            inp.conns.is_empty(),
            "{policy:?}: still holds the connection"
        );
    }
}

#[test]
fn an_event_port_is_woken_by_each_write_of_a_data_connection() {
    struct Count(std::sync::atomic::AtomicU64);
    impl crate::activity::Waker for Count {
        fn wake(&self) {
            self.0.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
        }
    }
    let count = Arc::new(Count(std::sync::atomic::AtomicU64::new(0)));
    let mut out = OutputPort::<f64>::new("out");
    let mut inp = InputPort::<f64>::new("in");
    let _ = inp.shared().waker.set(count.clone());
    connect(&out, &inp, ConnPolicy::data()).unwrap();
    for v in 0..3 {
        out.write(&f64::from(v));
    }
    assert!(out.push, "an event port's end is woken at each write");
    assert_eq!(count.0.load(std::sync::atomic::Ordering::Relaxed), 3);
    let mut x = 0.0;
    assert_eq!((inp.read(&mut x), x), (FlowStatus::NewData, 2.0));
}

#[test]
fn fan_out_and_fan_in() {
    let (mut a, mut b) = (OutputPort::<i32>::new("a"), OutputPort::<i32>::new("b"));
    let (mut i1, mut i2) = (InputPort::<i32>::new("i1"), InputPort::<i32>::new("i2"));
    connect(&a, &i1, ConnPolicy::buffer(8)).unwrap();
    connect(&a, &i2, ConnPolicy::buffer(8)).unwrap();
    connect(&b, &i1, ConnPolicy::buffer(8)).unwrap();
    a.write(&1);
    b.write(&10);
    a.write(&2);
    let mut got = drain(&mut i1);
    got.sort();
    assert_eq!(got, vec![1, 2, 10]);
    assert_eq!(drain(&mut i2), vec![1, 2]);
}

#[test]
fn an_end_that_goes_away_closes_its_connection() {
    let mut out = OutputPort::<i32>::new("out");
    let readers: Vec<InputPort<i32>> = (0..50)
        .map(|i| {
            let inp = InputPort::new(&format!("in{i}"));
            connect(&out, &inp, ConnPolicy::buffer(4)).unwrap();
            inp
        })
        .collect();
    out.write(&1);
    assert_eq!(out.connections().len(), 50);
    drop(readers);
    assert!(
        out.connections().is_empty(),
        "closed connections are not listed"
    );
    out.write(&2);
    assert!(
        out.conns.is_empty(),
        "the writer let go of every closed connection"
    );

    let mut inp = InputPort::<i32>::new("in");
    for _ in 0..10 {
        let w = OutputPort::<i32>::new("w");
        connect(&w, &inp, ConnPolicy::data()).unwrap();
        drop(w);
    }
    let mut x = 0;
    assert_eq!(inp.read(&mut x), FlowStatus::NoData);
    assert!(
        inp.conns.is_empty(),
        "the reader let go of every closed connection"
    );
}

#[test]
fn disconnect_at_run_time() {
    let (mut out, mut inp) = pair::<i32>(ConnPolicy::buffer(4));
    out.write(&1);
    assert_eq!(out.disconnect(None), 1);
    out.write(&2);
    let mut x = 0;
    assert_eq!(
        inp.read(&mut x),
        FlowStatus::NoData,
        "a closed connection delivers nothing"
    );
    assert!(inp.connections().is_empty());
    connect(&out, &inp, ConnPolicy::data()).unwrap();
    out.write(&3);
    assert_eq!((inp.read(&mut x), x), (FlowStatus::NewData, 3));
}

#[test]
fn zero_size_buffers_are_refused() {
    let out = OutputPort::<i32>::new("o");
    let inp = InputPort::<i32>::new("i");
    assert_eq!(
        connect(&out, &inp, ConnPolicy::buffer(0)).unwrap_err(),
        ConnectError::ZeroSize
    );
}

#[test]
fn writer_and_reader_on_two_threads_lose_nothing_in_order() {
    let (mut out, mut inp) = pair::<u64>(ConnPolicy::buffer(64));
    let n = 50_000u64;
    let writer = std::thread::spawn(move || {
        let mut v = 0;
        while v < n {
            // Only write when there is room, to test order, not dropping.
            if out.connections()[0].written - out.connections()[0].read < 60 {
                out.write(&v);
                v += 1;
            } else {
                std::thread::yield_now();
            }
        }
        out
    });
    let mut expect = 0;
    let mut x = 0;
    while expect < n {
        if inp.read(&mut x) == FlowStatus::NewData {
            assert_eq!(x, expect);
            expect += 1;
        }
    }
    let out = writer.join().unwrap();
    assert_eq!(out.connections()[0].dropped, 0);
}

/// A data connection across two threads, for a one-word type (the word register) and
/// for a wider one (the triple buffer): every new value read is one that was written,
/// in order, never torn, never the same write twice; the last one arrives.
fn data_across_threads<T: Clone + Send + Default + PartialEq + std::fmt::Debug + 'static>(
    make: fn(u64) -> T,
    key: fn(&T) -> u64,
) {
    let (mut out, mut inp) = pair::<T>(ConnPolicy::data());
    let n = 50_000u64;
    let writer = std::thread::spawn(move || {
        for v in 1..=n {
            out.write(&make(v));
        }
        out
    });
    let mut x = T::default();
    let mut last = 0;
    let mut news = 0u64;
    while last < n {
        if inp.read(&mut x) == FlowStatus::NewData {
            let k = key(&x);
            assert_eq!(x, make(k), "a torn sample: {x:?}");
            assert!(k > last, "{k} after {last}: not newer");
            last = k;
            news += 1;
        }
    }
    let _out = writer.join().unwrap();
    assert_eq!(
        inp.read(&mut x),
        FlowStatus::OldData,
        "nothing after the last"
    );
    assert!(news >= 1 && news <= n);
}

#[test]
fn data_connections_across_two_threads_are_whole_and_in_order() {
    data_across_threads::<u64>(|v| v, |x| *x);
    data_across_threads::<f64>(|v| v as f64 * 0.5, |x| (*x * 2.0) as u64);
    data_across_threads::<[u64; 8]>(|v| [v; 8], |x| x[0]);
}
