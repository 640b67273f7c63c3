//! What keeps a server bounded against its clients beyond the accept loop: a connection
//! whose writes stall too long fails ([`Stalling`]: a client that stops reading frees its
//! slot), work that must wait for the gateway takes a permit of a bounded pool
//! ([`Blocking`]: a client that asks and leaves cannot queue work without end), and a
//! request naming a host the server does not answer to is refused ([`host_allowed`]: a web
//! page of another site cannot reach a server on 127.0.0.1 through a name of its own).

use std::future::Future;
use std::io;
use std::pin::Pin;
use std::sync::Arc;
use std::sync::atomic::{AtomicU64, Ordering};
use std::task::{Context, Poll};
use std::time::Duration;
use tokio::io::{AsyncRead, AsyncWrite, ReadBuf};

/// How long a write may wait for its client to read.
pub const WRITE_STALL: Duration = Duration::from_secs(10);

/// A connection whose writes fail once one has waited [`WRITE_STALL`] for the client.
pub struct Stalling<T> {
    inner: T,
    stalled: Option<Pin<Box<tokio::time::Sleep>>>,
    count: Arc<AtomicU64>,
}

impl<T> Stalling<T> {
    /// `inner`, counting each stall that ends it in `count`.
    pub fn new(inner: T, count: Arc<AtomicU64>) -> Stalling<T> {
        Stalling {
            inner,
            stalled: None,
            count,
        }
    }

    /// The connection inside.
    pub fn get_ref(&self) -> &T {
        &self.inner
    }

    /// `Pending` until the stall has lasted too long, then the error that ends it.
    fn wait<R>(&mut self, cx: &mut Context<'_>, r: Poll<io::Result<R>>) -> Poll<io::Result<R>> {
        if r.is_ready() {
            self.stalled = None;
            return r;
        }
        let sleep = self
            .stalled
            .get_or_insert_with(|| Box::pin(tokio::time::sleep(WRITE_STALL)));
        if sleep.as_mut().poll(cx).is_ready() {
            self.count.fetch_add(1, Ordering::Relaxed);
            return Poll::Ready(Err(io::Error::new(
                io::ErrorKind::TimedOut,
                "the client stopped reading",
            )));
        }
        Poll::Pending
    }
}

impl<T: AsyncRead + Unpin> AsyncRead for Stalling<T> {
    fn poll_read(
        mut self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        buf: &mut ReadBuf<'_>,
    ) -> Poll<io::Result<()>> {
        Pin::new(&mut self.inner).poll_read(cx, buf)
    }
}

impl<T: AsyncWrite + Unpin> AsyncWrite for Stalling<T> {
    fn poll_write(
        mut self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        buf: &[u8],
    ) -> Poll<io::Result<usize>> {
        let r = Pin::new(&mut self.inner).poll_write(cx, buf);
        self.wait(cx, r)
    }

    fn poll_flush(mut self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<io::Result<()>> {
        let r = Pin::new(&mut self.inner).poll_flush(cx);
        self.wait(cx, r)
    }

    fn poll_shutdown(mut self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<io::Result<()>> {
        let r = Pin::new(&mut self.inner).poll_shutdown(cx);
        self.wait(cx, r)
    }
}

/// A bounded pool for work that waits for the gateway (a control request): a permit is
/// taken before the work is queued and given back when it ends — also when the client
/// that asked has gone meanwhile.
#[derive(Clone)]
pub struct Blocking(Arc<tokio::sync::Semaphore>);

/// Work under way or queued at once, per server.
pub const BLOCKING: usize = 8;

impl Blocking {
    /// A pool of [`BLOCKING`] permits.
    pub fn new() -> Blocking {
        Blocking(Arc::new(tokio::sync::Semaphore::new(BLOCKING)))
    }

    /// `f` on the runtime's blocking threads if a permit is free now; `None` (busy) if
    /// not, or if it panicked.
    pub async fn try_run<T: Send + 'static>(
        &self,
        f: impl FnOnce() -> T + Send + 'static,
    ) -> Option<T> {
        let permit = self.0.clone().try_acquire_owned().ok()?;
        run(permit, f).await
    }

    /// `f` on the runtime's blocking threads once a permit is free.
    pub async fn run<T: Send + 'static>(
        &self,
        f: impl FnOnce() -> T + Send + 'static,
    ) -> Option<T> {
        let permit = self.0.clone().acquire_owned().await.ok()?;
        run(permit, f).await
    }
}

impl Default for Blocking {
    fn default() -> Self {
        Blocking::new()
    }
}

async fn run<T: Send + 'static>(
    permit: tokio::sync::OwnedSemaphorePermit,
    f: impl FnOnce() -> T + Send + 'static,
) -> Option<T> {
    tokio::task::spawn_blocking(move || {
        let _permit = permit;
        f()
    })
    .await
    .ok()
}

/// True when a request's `Host` (`None`: none given) names an address, `localhost`, or
/// one of `names`: what a server answers to. A name of another site's (resolved to this
/// host by that site, to reach it from a browser) is not.
pub fn host_allowed(host: Option<&str>, names: &[String]) -> bool {
    let Some(host) = host else {
        return true;
    };
    let name = match host.strip_prefix('[') {
        // An IPv6 literal: [::1]:8088.
        Some(rest) => {
            return rest
                .split(']')
                .next()
                .is_some_and(|a| a.parse::<std::net::Ipv6Addr>().is_ok());
        }
        None => host.rsplit_once(':').map_or(host, |(n, _)| n),
    };
    name.parse::<std::net::IpAddr>().is_ok()
        || name.eq_ignore_ascii_case("localhost")
        || names.iter().any(|n| n.eq_ignore_ascii_case(name))
}

/// `a == b` in a time that does not tell where they differ (a token compared).
pub fn same(a: &[u8], b: &[u8]) -> bool {
    a.len() == b.len() && a.iter().zip(b).fold(0u8, |acc, (x, y)| acc | (x ^ y)) == 0
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn hosts_are_addresses_localhost_or_named() {
        let names = vec!["gw1.plant".to_string()];
        for ok in [
            None,
            Some("127.0.0.1:8088"),
            Some("[::1]:8088"),
            Some("localhost:1"),
            Some("GW1.plant:80"),
            Some("10.0.0.2"),
        ] {
            assert!(host_allowed(ok, &names), "{ok:?}");
        }
        for bad in [
            Some("evil.example:8088"),
            Some("evil.example"),
            Some("[nonsense]:1"),
            Some(""),
        ] {
            assert!(!host_allowed(bad, &names), "{bad:?}");
        }
    }
}
