//! Accepted connections with deadlines, so a client that connects and then stalls (half-sent
//! headers, no HTTP/2 preface, a stalled body, an idle keep-alive, answers never read) cannot
//! hold a socket and its memory for ever.
use std::future::Future;
use std::io;
use std::pin::Pin;
use std::sync::Arc;
use std::task::{Context, Poll};
use std::time::Duration;
use tokio::io::{AsyncRead, AsyncWrite, ReadBuf};
use tokio::net::{TcpListener, TcpStream};
use tokio::sync::{OwnedSemaphorePermit, Semaphore};
use tokio::time::{Instant, Sleep};

/// Deadlines for one connection.
#[derive(Clone, Copy, Debug)]
pub struct ConnLimits {
    /// The first `opening_bytes` must arrive within this (an HTTP/2 preface, a request line).
    pub opening: Duration,
    pub opening_bytes: usize,
    /// No byte read or written for this long while the server waits on the socket: closed.
    /// None for gRPC, whose idle channels are normal (HTTP/2 keep-alive pings find dead peers).
    pub idle: Option<Duration>,
}

/// A TCP stream that fails its pending read or write with `TimedOut` once a deadline passes.
pub struct Guarded {
    inner: TcpStream,
    limits: ConnLimits,
    read: usize,
    timer: Pin<Box<Sleep>>,
    /// The connection's place under the server's connection limit, freed when it closes.
    _slot: OwnedSemaphorePermit,
}

impl Guarded {
    pub fn new(inner: TcpStream, limits: ConnLimits, slot: OwnedSemaphorePermit) -> Self {
        let timer = Box::pin(tokio::time::sleep(limits.opening));
        Self { inner, limits, read: 0, timer, _slot: slot }
    }

    pub fn get_ref(&self) -> &TcpStream {
        &self.inner
    }

    /// The deadline now in force: the opening one until its bytes are in, then idleness.
    fn rearm(&mut self) {
        if self.read < self.limits.opening_bytes {
            return;
        }
        if let Some(idle) = self.limits.idle {
            self.timer.as_mut().reset(Instant::now() + idle);
        }
    }

    fn expired(&mut self, cx: &mut Context<'_>) -> bool {
        let waiting_on_opening = self.read < self.limits.opening_bytes;
        (waiting_on_opening || self.limits.idle.is_some()) && self.timer.as_mut().poll(cx).is_ready()
    }

    fn timed_out(&self) -> io::Error {
        let what = if self.read < self.limits.opening_bytes { "opening bytes" } else { "idle connection" };
        io::Error::new(io::ErrorKind::TimedOut, format!("{what}: deadline passed"))
    }
}

impl AsyncRead for Guarded {
    fn poll_read(mut self: Pin<&mut Self>, cx: &mut Context<'_>, buf: &mut ReadBuf<'_>) -> Poll<io::Result<()>> {
        let before = buf.filled().len();
        match Pin::new(&mut self.inner).poll_read(cx, buf) {
            Poll::Ready(Ok(())) => {
                self.read += buf.filled().len() - before;
                self.rearm();
                Poll::Ready(Ok(()))
            }
            Poll::Pending if self.expired(cx) => Poll::Ready(Err(self.timed_out())),
            other => other,
        }
    }
}

impl AsyncWrite for Guarded {
    fn poll_write(mut self: Pin<&mut Self>, cx: &mut Context<'_>, buf: &[u8]) -> Poll<io::Result<usize>> {
        match Pin::new(&mut self.inner).poll_write(cx, buf) {
            Poll::Ready(Ok(n)) => {
                self.rearm();
                Poll::Ready(Ok(n))
            }
            // A client that never reads its answers: the socket's buffer stays full.
            Poll::Pending if self.expired(cx) => Poll::Ready(Err(self.timed_out())),
            other => other,
        }
    }

    fn poll_flush(mut self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<io::Result<()>> {
        Pin::new(&mut self.inner).poll_flush(cx)
    }

    fn poll_shutdown(mut self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<io::Result<()>> {
        Pin::new(&mut self.inner).poll_shutdown(cx)
    }

    fn poll_write_vectored(
        mut self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        bufs: &[io::IoSlice<'_>],
    ) -> Poll<io::Result<usize>> {
        match Pin::new(&mut self.inner).poll_write_vectored(cx, bufs) {
            Poll::Ready(Ok(n)) => {
                self.rearm();
                Poll::Ready(Ok(n))
            }
            Poll::Pending if self.expired(cx) => Poll::Ready(Err(self.timed_out())),
            other => other,
        }
    }

    fn is_write_vectored(&self) -> bool {
        self.inner.is_write_vectored()
    }
}

impl tonic::transport::server::Connected for Guarded {
    type ConnectInfo = tonic::transport::server::TcpConnectInfo;

    fn connect_info(&self) -> Self::ConnectInfo {
        self.inner.connect_info()
    }
}

/// Accepts the next connection that fits under the limit (beyond it, connections are closed at
/// once and logged), with TCP_NODELAY (no Nagle: small answers leave at once instead of waiting
/// for the client's delayed ACK) and the deadlines.
pub async fn accept(listener: &TcpListener, limits: ConnLimits, slots: &Slots) -> Guarded {
    loop {
        let (tcp, peer) = match listener.accept().await {
            Ok(c) => c,
            Err(e) => {
                // Out of file descriptors, say: wait a little instead of spinning.
                tracing::warn!(error = %e, "accept failed");
                tokio::time::sleep(Duration::from_millis(50)).await;
                continue;
            }
        };
        let Ok(slot) = slots.free.clone().try_acquire_owned() else {
            tracing::warn!(%peer, "connection refused: the connection limit is reached");
            continue;
        };
        if let Err(e) = tcp.set_nodelay(true) {
            tracing::debug!(error = %e, "TCP_NODELAY not set");
        }
        return Guarded::new(tcp, limits, slot);
    }
}

/// The connection limit of one listener, and how much of it is in use (`/metrics`).
#[derive(Debug)]
pub struct Slots {
    free: Arc<Semaphore>,
    max: usize,
}

impl Slots {
    pub fn new(max: usize) -> Arc<Self> {
        let max = max.max(1);
        Arc::new(Self { free: Arc::new(Semaphore::new(max)), max })
    }

    /// Connections open now (accepted and not yet closed).
    pub fn open(&self) -> usize {
        self.max - self.free.available_permits()
    }

    pub fn max(&self) -> usize {
        self.max
    }
}

/// Both listeners' limits.
#[derive(Debug)]
pub struct Connections {
    pub http: Arc<Slots>,
    pub grpc: Arc<Slots>,
}

impl Connections {
    pub fn new(max_per_listener: usize) -> Self {
        Self { http: Slots::new(max_per_listener), grpc: Slots::new(max_per_listener) }
    }
}

/// Open connections and the limit, per listener (`/metrics`).
impl prometheus_client::collector::Collector for Connections {
    fn encode(&self, mut encoder: prometheus_client::encoding::DescriptorEncoder) -> std::fmt::Result {
        use prometheus_client::encoding::EncodeMetric;
        use prometheus_client::metrics::{gauge::ConstGauge, MetricType};
        type Value = fn(&Slots) -> usize;
        let gauges: [(&str, &str, Value); 2] = [
            ("loopd_open_connections", "Connections open now, per listener.", Slots::open),
            ("loopd_max_connections", "The connection limit, per listener (beyond it, closed at once).", Slots::max),
        ];
        for (name, help, value) in gauges {
            let mut family = encoder.encode_descriptor(name, help, None, MetricType::Gauge)?;
            for (listener, s) in [("http", &self.http), ("grpc", &self.grpc)] {
                ConstGauge::new(value(s) as i64).encode(family.encode_family(&[("listener", listener)])?)?;
            }
        }
        Ok(())
    }
}
