//! Modbus at scale (`cargo bench -p hwgw --bench modbus_load`), the real binary, each
//! figure beside a reference from the same run. Runs `MODBUS_BENCH_SECONDS` each (default
//! 10).
//!
//! **The server.** hwgw serves ten holding registers (FC3 reads of all ten); pymodbus's
//! Modbus TCP server (Debian's python3-pymodbus, the tests' peer) serves the same read
//! as the reference. The masters are this bench's own load generator: one tokio task a
//! master on one thread, each with its connection and one request outstanding, back to
//! back, every reply checked (its transaction id, and the ten registers as mbpoll — a
//! libmodbus master — read them first). With 1, 10 and 100 masters: requests a second,
//! p50 and p99 latency, the server's CPU (all its threads, % of one core) and resident
//! memory, and the generator's CPU. A third server is the floor: this bench's own process
//! answering every request with the same canned reply on one tokio thread, as hwgw's
//! server is built, with no table, checks or counters — what the loopback, the generator
//! and the runtime allow on this machine.
//!
//! **The client.** hwgw polls pymodbus units over Modbus TCP: ten units of 1 000 points
//! each (u16 input registers 0-999: eight reads a poll) every second, then one unit of
//! 1 000 points every 100 ms — the scenarios EMQX NeuronEX publishes. hwgw's CPU and
//! memory, the units' poll lateness (p99 and max from `hwgw status`, µs) and the polls it
//! made, beside the reference: the same binary running one simulated card. Each card's IO
//! component samples its channels at its poll period.

#![allow(
    clippy::unwrap_used,
    reason = "bench code: a failed unwrap is a failed run"
)]

use std::net::SocketAddr;
use std::time::{Duration, Instant};
use testkit::Service;
use testkit::bench::{ProcUsage, proc_usage};
use testkit::pymodbus::PyModbus;
use tokio::io::{AsyncReadExt, AsyncWriteExt};

const HWGW: &str = env!("CARGO_BIN_EXE_hwgw");
/// FC3, ten registers from 0.
const REQUEST: [u8; 5] = [3, 0, 0, 0, 10];

fn seconds() -> f64 {
    std::env::var("MODBUS_BENCH_SECONDS")
        .ok()
        .and_then(|s| s.parse().ok())
        .unwrap_or(10.0)
}

/// hwgw serving ten holding registers, 1000 + 111 × n at register n.
fn served() -> String {
    let mut t =
        String::from("[[card]]\nname = \"sim0\"\ndriver = \"sim\"\nperiod_ms = 100\n[card.sim]\n");
    for n in 0..10 {
        t += &format!(
            "[[card.sim.analog_out]]\nrange = {{ lowest = 0.0, highest = 65535.0 }}\n\
             raw = {{ min = 0, max = 65535 }}\ninitial = {}.0\n",
            1000 + 111 * n
        );
    }
    t += "[modbus_server]\nlisten = \"127.0.0.1:0\"\nmax_clients = 128\nmax_clients_per_address = 128\n";
    for n in 0..10 {
        t += &format!(
            "[[modbus_server.register]]\ntable = \"holding_registers\"\naddress = {n}\n\
             device = \"sim0\"\ninterface = \"analog_out\"\nchannel = {n}\n"
        );
    }
    t
}

/// The ten registers as mbpoll reads them from `port`.
fn mbpoll(port: u16) -> Vec<u16> {
    let out = testkit::mbpoll::Mbpoll {
        port,
        table: "4",
        address: 0,
        count: Some(10),
        write: &[],
    }
    .run();
    let regs: Vec<u16> = out
        .lines()
        .filter_map(|l| l.strip_prefix('['))
        .filter_map(|l| l.split_once("]: \t"))
        .map(|(_, v)| v.split(' ').next().unwrap().parse().unwrap())
        .collect();
    assert_eq!(regs.len(), 10, "mbpoll read: {out}");
    regs
}

/// One master for `seconds`: its latencies, µs; every reply the registers `want`.
async fn master(addr: SocketAddr, seconds: f64, want: Vec<u16>) -> Vec<u32> {
    let mut s = tokio::net::TcpStream::connect(addr).await.unwrap();
    s.set_nodelay(true).unwrap();
    let mut frame = vec![0, 0, 0, 0, 0, (REQUEST.len() + 1) as u8, 1];
    frame.extend_from_slice(&REQUEST);
    let mut expect = [0u8; 7 + 2 + 20];
    expect[7..9].copy_from_slice(&[3, 20]);
    for (i, r) in want.iter().enumerate() {
        expect[9 + 2 * i..11 + 2 * i].copy_from_slice(&r.to_be_bytes());
    }
    let mut reply = vec![0u8; expect.len()];
    let (mut lat, mut tid) = (Vec::with_capacity(1 << 20), 0u16);
    let end = Instant::now() + Duration::from_secs_f64(seconds);
    while Instant::now() < end {
        tid = tid.wrapping_add(1);
        frame[..2].copy_from_slice(&tid.to_be_bytes());
        let t0 = Instant::now();
        s.write_all(&frame).await.unwrap();
        s.read_exact(&mut reply).await.unwrap();
        lat.push(t0.elapsed().as_micros() as u32);
        assert_eq!(&reply[..2], &tid.to_be_bytes(), "the transaction id echoed");
        assert_eq!(&reply[7..], &expect[7..], "the ten registers");
    }
    lat
}

/// One load run's figures.
struct Load {
    rate: f64,
    p50: u32,
    p99: u32,
    server_cpu: f64,
    server_rss_mib: f64,
    generator_cpu: f64,
}

/// `n` masters against `addr` (the server process `pid`) for `seconds`.
fn load(addr: SocketAddr, pid: u32, n: usize, seconds: f64, want: &[u16]) -> Load {
    let rt = tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()
        .unwrap();
    let me = std::process::id();
    let (a, ma, t0) = (
        proc_usage(pid).unwrap(),
        proc_usage(me).unwrap(),
        Instant::now(),
    );
    let mut all: Vec<u32> = rt.block_on(async {
        let mut set = tokio::task::JoinSet::new();
        for _ in 0..n {
            set.spawn(master(addr, seconds, want.to_vec()));
        }
        let mut all = Vec::new();
        while let Some(r) = set.join_next().await {
            all.extend(r.unwrap());
        }
        all
    });
    let s = t0.elapsed().as_secs_f64();
    let (b, mb): (ProcUsage, ProcUsage) = (proc_usage(pid).unwrap(), proc_usage(me).unwrap());
    all.sort_unstable();
    let q = |p: f64| all[((all.len() as f64 * p) as usize).min(all.len() - 1)];
    Load {
        rate: all.len() as f64 / s,
        p50: q(0.5),
        p99: q(0.99),
        server_cpu: b.cpu_percent_since(a, s),
        server_rss_mib: b.rss_kib as f64 / 1024.0,
        generator_cpu: mb.cpu_percent_since(ma, s),
    }
}

fn server_bench(seconds: f64) {
    let hwgw = Service::run_text(HWGW, "modbus-bench-server", &served()).unwrap();
    let addr = hwgw.wait_listening("modbus_server");
    let want = mbpoll(addr.port());
    let expected: Vec<u16> = (0..10).map(|n| 1000 + 111 * n).collect();
    assert_eq!(want, expected, "mbpoll reads what the card holds");
    let py = PyModbus::start("pattern_tcp");
    let py_want = mbpoll(py.addr.port());
    println!("Modbus TCP servers, FC3 read of 10 registers, {seconds} s a run");
    println!(
        "{:>7} | {:>9} {:>6} {:>6} {:>6} {:>7} {:>5} | {:>9} {:>6} {:>6} {:>6} {:>7} {:>5} | {:>6}",
        "masters",
        "hwgw/s",
        "p50µs",
        "p99µs",
        "CPU%",
        "RSS MiB",
        "gen%",
        "pymodbus",
        "p50µs",
        "p99µs",
        "CPU%",
        "RSS MiB",
        "gen%",
        "ratio"
    );
    let floor = floor();
    let zeros = vec![0u16; 10];
    for n in [1, 10, 100] {
        let h = load(addr, hwgw.pid().unwrap(), n, seconds, &want);
        let p = load(py.addr, py.pid(), n, seconds, &py_want);
        let f = load(floor.1, floor.0.id(), n, seconds, &zeros);
        println!(
            "{n:>7} | {:>9.0} {:>6} {:>6} {:>6.1} {:>7.1} {:>5.0} | {:>9.0} {:>6} {:>6} {:>6.1} {:>7.1} {:>5.0} | {:>6.1}",
            h.rate,
            h.p50,
            h.p99,
            h.server_cpu,
            h.server_rss_mib,
            h.generator_cpu,
            p.rate,
            p.p50,
            p.p99,
            p.server_cpu,
            p.server_rss_mib,
            p.generator_cpu,
            h.rate / p.rate
        );
        println!(
            "{:>7} | floor {:>9.0}/s p50 {} µs p99 {} µs, its CPU {:.1}%, generator {:.0}%: hwgw at {:.2}x the floor's rate",
            "",
            f.rate,
            f.p50,
            f.p99,
            f.server_cpu,
            f.generator_cpu,
            h.rate / f.rate
        );
    }
}

/// A Modbus card of 1 000 u16 input registers (0-999) on `addr`, polled every `poll_ms`;
/// its IO component samples the channels as often (`period_ms`).
fn unit_card(name: &str, addr: SocketAddr, poll_ms: u32) -> String {
    let mut t = format!(
        "[[card]]\nname = \"{name}\"\ndriver = \"modbus\"\nperiod_ms = {poll_ms}\n[card.modbus]\n\
         transport = {{ type = \"tcp\", address = \"{addr}\" }}\npoll_ms = {poll_ms}\ntimeout_ms = 1000\n"
    );
    for a in 0..1000 {
        t += &format!("[[card.modbus.point]]\ntable = \"input_registers\"\naddress = {a}\n");
    }
    t
}

/// A run of the client: hwgw's CPU, RSS, and its units' polls, p99 and max lateness.
fn client_run(name: &str, deployment: &str, seconds: f64, units: &[PyModbus]) {
    let tag = format!("modbus-bench-{}", name.split(' ').next().unwrap_or("run"));
    let hwgw = Service::run_text(HWGW, &tag, deployment).unwrap();
    let status = || -> serde_json::Value {
        serde_json::from_str(&hwgw.out(&["status", "--json"]).unwrap()).unwrap()
    };
    let cards = |s: &serde_json::Value| -> Vec<serde_json::Value> {
        s["cards"].as_array().cloned().unwrap_or_default()
    };
    // Warmed up: every unit polled.
    testkit::wait_until("every unit polled", || {
        cards(&status())
            .iter()
            .all(|c| c["driver"] != "modbus" || c["counters"]["polls"].as_u64() >= Some(2))
    });
    let pid = hwgw.pid().unwrap();
    let pys: Vec<u32> = units.iter().map(PyModbus::pid).collect();
    let py_cpu = |v: &[ProcUsage], w: &[ProcUsage], s: f64| -> f64 {
        v.iter()
            .zip(w)
            .map(|(a, b)| b.cpu_percent_since(*a, s))
            .sum()
    };
    let polls = |s: &serde_json::Value| -> u64 {
        cards(s)
            .iter()
            .filter_map(|c| c["counters"]["polls"].as_u64())
            .sum()
    };
    let s0 = status();
    let (a, pa, t0) = (
        proc_usage(pid).unwrap(),
        pys.iter()
            .map(|p| proc_usage(*p).unwrap())
            .collect::<Vec<_>>(),
        Instant::now(),
    );
    std::thread::sleep(Duration::from_secs_f64(seconds));
    let (b, pb) = (
        proc_usage(pid).unwrap(),
        pys.iter()
            .map(|p| proc_usage(*p).unwrap())
            .collect::<Vec<_>>(),
    );
    let s = t0.elapsed().as_secs_f64();
    let s1 = status();
    let (mut p99, mut max, mut failed) = (0u64, 0u64, 0u64);
    for c in cards(&s1) {
        let k = &c["counters"];
        p99 = p99.max(k["poll_lateness_p99_us"].as_u64().unwrap_or(0));
        max = max.max(k["poll_lateness_max_us"].as_u64().unwrap_or(0));
        failed += k["timeouts"].as_u64().unwrap_or(0) + k["transport_errors"].as_u64().unwrap_or(0);
    }
    println!(
        "{name:<28} | hwgw {:>5.1}% CPU {:>6.1} MiB | {:>6.1} polls/s, lateness p99 {:>6} µs max {:>7} µs, {failed} failed | pymodbus units {:>5.1}% CPU",
        b.cpu_percent_since(a, s),
        b.rss_kib as f64 / 1024.0,
        (polls(&s1) - polls(&s0)) as f64 / s,
        p99,
        max,
        py_cpu(&pa, &pb, s),
    );
}

fn client_bench(seconds: f64) {
    let units: Vec<PyModbus> = (0..10).map(|_| PyModbus::start("pattern_tcp")).collect();
    println!(
        "hwgw polling pymodbus units over Modbus TCP, {seconds} s a run (lateness since start)"
    );
    let reference = "[[card]]\nname = \"sim0\"\ndriver = \"sim\"\n[card.sim]\ndigital_inputs = 1\n";
    client_run("reference (one sim card)", reference, seconds, &[]);
    let ten: String = units
        .iter()
        .enumerate()
        .map(|(i, u)| unit_card(&format!("unit{i}"), u.addr, 1000))
        .collect();
    client_run("10 units x 1000 points, 1 s", &ten, seconds, &units);
    let one = unit_card("unit0", units[0].addr, 100);
    client_run("1 unit x 1000 points, 100 ms", &one, seconds, &units[..1]);
}

/// The floor: a server process that reads each 12-byte request and writes the canned
/// 29-byte reply with its transaction id, on one tokio thread; prints its port.
fn echo_server() {
    let rt = tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()
        .unwrap();
    rt.block_on(async {
        let l = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
        println!("{}", l.local_addr().unwrap().port());
        loop {
            let (mut s, _) = l.accept().await.unwrap();
            tokio::spawn(async move {
                let _ = s.set_nodelay(true);
                let mut req = [0u8; 12];
                let mut reply = [0u8; 29];
                reply[5] = 23;
                reply[6] = 1;
                reply[7..9].copy_from_slice(&[3, 20]);
                while s.read_exact(&mut req).await.is_ok() {
                    reply[..2].copy_from_slice(&req[..2]);
                    if s.write_all(&reply).await.is_err() {
                        break;
                    }
                }
            });
        }
    });
}

/// The floor server as a process of its own, and where it listens.
struct Floor(std::process::Child, SocketAddr);

impl Drop for Floor {
    fn drop(&mut self) {
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}

fn floor() -> Floor {
    use std::io::BufRead;
    let mut child = std::process::Command::new(std::env::current_exe().unwrap())
        .env("MODBUS_BENCH_FLOOR", "1")
        .stdout(std::process::Stdio::piped())
        .spawn()
        .unwrap();
    let mut line = String::new();
    std::io::BufReader::new(child.stdout.take().unwrap())
        .read_line(&mut line)
        .unwrap();
    let port: u16 = line.trim().parse().unwrap();
    Floor(child, SocketAddr::from(([127, 0, 0, 1], port)))
}

fn main() {
    if std::env::args().any(|a| a == "--list" || a == "--test") {
        return;
    }
    if std::env::var_os("MODBUS_BENCH_FLOOR").is_some() {
        return echo_server();
    }
    let seconds = seconds();
    server_bench(seconds);
    client_bench(seconds);
}
