//! A Modbus TCP server for tests and benchmarks (feature `test-server`): tokio-modbus's
//! server over an in-memory register table, with injectable faults — silent units and
//! exception replies — on a thread and runtime of its own.
//!
//! ```
//! use driver_modbus::testing::TestServer;
//!
//! let server = TestServer::start();
//! server.memory().lock().unwrap().input[0] = 42;
//! // ... point a line (TestLine::spawn) at server.addr() ...
//! ```

#![allow(
    clippy::unwrap_used,
    reason = "test scaffolding: a failed unwrap fails the test that uses it"
)]

use std::collections::HashSet;
use std::future::Future;
use std::net::SocketAddr;
use std::pin::Pin;
use std::sync::{Arc, Mutex};
use std::time::Duration;
use tokio_modbus::server::tcp::{Server, accept_tcp_connection};
use tokio_modbus::{ExceptionCode, Request, Response, SlaveRequest};

/// The server's registers and fault switches.
#[derive(Default)]
pub struct Memory {
    /// Input registers.
    pub input: Vec<u16>,
    /// Holding registers.
    pub holding: Vec<u16>,
    /// Coils.
    pub coils: Vec<bool>,
    /// Discrete inputs.
    pub discrete: Vec<bool>,
    /// Units that never answer.
    pub silent: HashSet<u8>,
    /// Answer reads of holding registers with this exception.
    pub holding_exception: Option<ExceptionCode>,
    /// Answer writes (function codes 5, 6, 15, 16) with this exception, writing nothing.
    pub write_exception: Option<ExceptionCode>,
    /// Never answer writes, writing nothing (reads are answered).
    pub silent_writes: bool,
    /// Write requests received, answered or not.
    pub writes: u64,
    /// Requests seen, by unit.
    pub seen: Vec<u8>,
}

#[derive(Clone)]
struct Svc(Arc<Mutex<Memory>>);

impl tokio_modbus::server::Service for Svc {
    type Request = SlaveRequest<'static>;
    type Response = Option<Response>;
    type Exception = ExceptionCode;
    type Future = Pin<Box<dyn Future<Output = Result<Option<Response>, ExceptionCode>> + Send>>;

    fn call(&self, req: SlaveRequest<'static>) -> Self::Future {
        let mem = self.0.clone();
        Box::pin(async move {
            let mut m = mem.lock().unwrap();
            m.seen.push(req.slave);
            if m.silent.contains(&req.slave) {
                return Ok(None);
            }
            if matches!(
                req.request,
                Request::WriteSingleCoil(..)
                    | Request::WriteMultipleCoils(..)
                    | Request::WriteSingleRegister(..)
                    | Request::WriteMultipleRegisters(..)
            ) {
                m.writes += 1;
                if m.silent_writes {
                    return Ok(None);
                }
                if let Some(code) = m.write_exception {
                    return Err(code);
                }
            }
            let range = |a: u16, n: u16| usize::from(a)..usize::from(a) + usize::from(n);
            Ok(Some(match req.request {
                Request::ReadInputRegisters(a, n) => {
                    Response::ReadInputRegisters(m.input[range(a, n)].to_vec())
                }
                Request::ReadHoldingRegisters(a, n) => {
                    if let Some(code) = m.holding_exception {
                        return Err(code);
                    }
                    Response::ReadHoldingRegisters(m.holding[range(a, n)].to_vec())
                }
                Request::ReadCoils(a, n) => Response::ReadCoils(m.coils[range(a, n)].to_vec()),
                Request::ReadDiscreteInputs(a, n) => {
                    Response::ReadDiscreteInputs(m.discrete[range(a, n)].to_vec())
                }
                Request::WriteSingleCoil(a, v) => {
                    m.coils[usize::from(a)] = v;
                    Response::WriteSingleCoil(a, v)
                }
                Request::WriteMultipleCoils(a, vs) => {
                    m.coils[range(a, vs.len() as u16)].copy_from_slice(&vs);
                    Response::WriteMultipleCoils(a, vs.len() as u16)
                }
                Request::WriteSingleRegister(a, v) => {
                    m.holding[usize::from(a)] = v;
                    Response::WriteSingleRegister(a, v)
                }
                Request::WriteMultipleRegisters(a, vs) => {
                    m.holding[range(a, vs.len() as u16)].copy_from_slice(&vs);
                    Response::WriteMultipleRegisters(a, vs.len() as u16)
                }
                _ => return Err(ExceptionCode::IllegalFunction),
            }))
        })
    }
}

/// A server on 127.0.0.1 with its own runtime; stops when dropped.
pub struct TestServer {
    addr: SocketAddr,
    mem: Arc<Mutex<Memory>>,
    stop: Option<tokio::sync::oneshot::Sender<()>>,
    thread: Option<std::thread::JoinHandle<()>>,
}

impl TestServer {
    /// A server on a free port with 200 registers and 64 bits of each kind.
    pub fn start() -> TestServer {
        let mem = Arc::new(Mutex::new(Memory {
            input: vec![0; 200],
            holding: vec![0; 200],
            coils: vec![false; 64],
            discrete: vec![false; 64],
            ..Memory::default()
        }));
        Self::start_on(mem, "127.0.0.1:0".parse().unwrap())
    }

    /// A server on `at` over `mem` (restart one at its old address with its old memory).
    pub fn start_on(mem: Arc<Mutex<Memory>>, at: SocketAddr) -> TestServer {
        let (tx, rx) = tokio::sync::oneshot::channel::<()>();
        let (addr_tx, addr_rx) = std::sync::mpsc::channel();
        let m = mem.clone();
        let thread = std::thread::spawn(move || {
            let rt = tokio::runtime::Builder::new_multi_thread()
                .worker_threads(1)
                .enable_all()
                .build()
                .unwrap();
            rt.block_on(async move {
                // Re-binding an old port can race another socket for it: retry a while.
                let deadline = std::time::Instant::now() + Duration::from_secs(10);
                let listener = loop {
                    match tokio::net::TcpListener::bind(at).await {
                        Ok(l) => break l,
                        Err(e) if std::time::Instant::now() < deadline => {
                            let _ = e;
                            tokio::time::sleep(Duration::from_millis(50)).await;
                        }
                        Err(e) => panic!("test server: cannot bind {at}: {e}"),
                    }
                };
                addr_tx.send(listener.local_addr().unwrap()).unwrap();
                let server = Server::new(listener);
                let svc = Svc(m);
                let on_connected = |stream, socket_addr| {
                    let svc = svc.clone();
                    async move { accept_tcp_connection(stream, socket_addr, |_| Ok(Some(svc.clone()))) }
                };
                let abort = async move {
                    let _ = rx.await;
                };
                let _ = server.serve_until(&on_connected, |_| {}, abort).await;
            });
        });
        let addr = addr_rx.recv_timeout(Duration::from_secs(5)).unwrap();
        TestServer {
            addr,
            mem,
            stop: Some(tx),
            thread: Some(thread),
        }
    }
}

impl TestServer {
    /// Where it listens.
    pub fn addr(&self) -> SocketAddr {
        self.addr
    }

    /// Its registers and fault switches.
    pub fn memory(&self) -> &Arc<Mutex<Memory>> {
        &self.mem
    }
}

impl Drop for TestServer {
    fn drop(&mut self) {
        if let Some(s) = self.stop.take() {
            let _ = s.send(());
        }
        if let Some(t) = self.thread.take() {
            let _ = t.join();
        }
    }
}

/// A Modbus line polling on a runtime of its own, for tests and benchmarks: the
/// [`LineIo`](crate::component::LineIo) component, started. Dropping it stops the line
/// (after the poll under way).
pub struct TestLine {
    _runtime: rtt::Runtime,
    task: rtt::TaskContext,
}

impl TestLine {
    /// Starts polling `units` over `transport` as component `name`.
    pub fn spawn(
        name: &str,
        transport: crate::line::Transport,
        units: Vec<crate::line::LineUnit>,
    ) -> Result<TestLine, Box<dyn std::error::Error>> {
        let runtime = rtt::Runtime::new(
            Arc::new(device_interface::Registry::new()),
            rtt::RuntimeOptions::default(),
        )?;
        let task = crate::component::LineIo::add(
            &runtime,
            name,
            transport,
            units,
            rtt::ThreadOptions::default(),
        )?;
        task.start()?;
        Ok(TestLine {
            _runtime: runtime,
            task,
        })
    }

    /// The line's component.
    pub fn task(&self) -> &rtt::TaskContext {
        &self.task
    }
}

/// A card over the register map in `map` (TOML with `[[point]]` tables, as a card's
/// section has them), coalescing reads across gaps of up to `max_gap` addresses.
pub fn card(map: &str, max_gap: u16) -> Arc<crate::card::ModbusCard> {
    let t: toml::Table = toml::from_str(map).unwrap();
    let points: Vec<crate::map::PointConfig> = t["point"].clone().try_into().unwrap();
    crate::card::ModbusCard::new(
        crate::map::Map::new(&points, max_gap).unwrap(),
        Arc::new(device_interface::time::MonotonicClock),
    )
}
