//! The farm's front door: every connection and every call passes here before
//! any body is read.
//!
//! First, every request passes the `Host` and `Origin` checks of
//! [`crate::guard::Hosts`] (refused with 400 or 403, a gRPC call with
//! `PERMISSION_DENIED`): without a token only loopback names and
//! `--allow-host` names are served, and a foreign `Origin` changes nothing.
//!
//! With a token, a connection is *unauthenticated* until one of its requests
//! carries `Authorization: Bearer <token>` (or, for the studio's event
//! stream alone, `?token=<token>`; see [`crate::guard::admits`]). Unauthenticated connections are limited in
//! number ([`GateLimits::unauthenticated`]); when one more arrives, the
//! oldest of the peer address holding the most of them is closed, so a flood
//! from one address cannot keep another address out. An unauthenticated
//! connection is also closed when its handshake time
//! ([`GateLimits::handshake`]) runs out, whatever it is doing. A gRPC call
//! without the token is refused (`UNAUTHENTICATED`) from its headers, before
//! a byte of its body is read; refusals are logged at most once a minute for
//! each peer address, with the number refused since the last line.
//!
//! Without a token (loopback only, see `farm::Farm::start`) every connection
//! counts as authenticated and none of the token's rules apply.

use std::collections::HashMap;
use std::future::Future;
use std::net::{IpAddr, SocketAddr};
use std::pin::Pin;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use std::task::{Context, Poll, Waker};
use std::time::{Duration, Instant};

use axum::http::{Request, Response};
use tokio::io::{AsyncRead, AsyncWrite, ReadBuf};
use tokio::net::{TcpListener, TcpStream};
use tonic::transport::server::{Connected, TcpConnectInfo};

/// How many unauthenticated connections, and for how long.
#[derive(Clone, Copy, Debug)]
pub struct GateLimits {
    /// Unauthenticated connections held at once.
    pub unauthenticated: usize,
    /// How long a connection may stay unauthenticated (the TCP, TLS and
    /// HTTP/2 handshakes and a first call with the token fit in it).
    pub handshake: Duration,
}

impl Default for GateLimits {
    fn default() -> GateLimits {
        GateLimits {
            unauthenticated: 64,
            handshake: Duration::from_secs(5),
        }
    }
}

/// How often a peer's refusals are logged.
const LOG_EVERY: Duration = Duration::from_secs(60);
/// Peers whose refusals are remembered for [`LOG_EVERY`]; beyond them a
/// refusal is counted but not logged.
const LOG_PEERS: usize = 1024;

/// One accepted connection's state, shared by its stream and the gate.
#[derive(Debug, Default)]
struct Conn {
    /// A request of it carried the token.
    authenticated: AtomicBool,
    /// The gate closed it: its next read or write fails.
    closed: AtomicBool,
    /// The reader to wake when the gate closes it.
    waker: Mutex<Option<Waker>>,
}

impl Conn {
    fn close(&self) {
        self.closed.store(true, Ordering::Release);
        if let Some(w) = self.waker.lock().unwrap_or_else(|p| p.into_inner()).take() {
            w.wake();
        }
    }
}

/// Refusals of one peer address since its last log line.
struct Refusals {
    logged: Instant,
    since: u64,
}

/// The connections the gate knows of.
#[derive(Default)]
struct Conns {
    /// Every open connection, by its peer address (unique while it is open).
    open: HashMap<SocketAddr, (u64, Arc<Conn>)>,
    /// Arrival order of connections.
    next: u64,
}

/// The gate: the token, the limits, the connections and the refusals.
pub struct Gate {
    token: Option<Vec<u8>>,
    /// The `Host` and `Origin` rules.
    hosts: crate::guard::Hosts,
    limits: GateLimits,
    conns: Mutex<Conns>,
    refusals: Mutex<HashMap<IpAddr, Refusals>>,
    /// Calls refused for a missing or wrong token.
    refused: AtomicU64,
    /// Connections closed unauthenticated (evicted or past their handshake time).
    closed: AtomicU64,
}

impl Gate {
    /// A gate for `token` (none: loopback only) that serves `allow_hosts`
    /// besides loopback names when there is no token.
    pub fn new(token: Option<&str>, limits: GateLimits, allow_hosts: &[String]) -> Arc<Gate> {
        Arc::new(Gate {
            token: token.map(|t| t.as_bytes().to_vec()),
            hosts: crate::guard::Hosts::new(allow_hosts, token.is_some()),
            limits,
            conns: Mutex::default(),
            refusals: Mutex::default(),
            refused: AtomicU64::new(0),
            closed: AtomicU64::new(0),
        })
    }

    /// Calls refused for a missing or wrong token so far.
    pub fn refused(&self) -> u64 {
        self.refused.load(Ordering::Relaxed)
    }

    /// Unauthenticated connections closed so far.
    pub fn closed(&self) -> u64 {
        self.closed.load(Ordering::Relaxed)
    }

    /// Takes in an accepted connection, closing the oldest unauthenticated
    /// connection of the busiest peer address when the limit is reached.
    fn admit(self: &Arc<Gate>, stream: TcpStream) -> GatedStream {
        let peer = stream.peer_addr().ok();
        let conn = Arc::new(Conn::default());
        if self.token.is_none() {
            conn.authenticated.store(true, Ordering::Relaxed);
        }
        if let Some(peer) = peer {
            let mut conns = self.conns.lock().unwrap_or_else(|p| p.into_inner());
            if self.token.is_some() {
                let waiting: Vec<(SocketAddr, u64)> = conns
                    .open
                    .iter()
                    .filter(|(_, (_, c))| {
                        !c.authenticated.load(Ordering::Acquire)
                            && !c.closed.load(Ordering::Acquire)
                    })
                    .map(|(a, (n, _))| (*a, *n))
                    .collect();
                if waiting.len() >= self.limits.unauthenticated {
                    let mut per_ip: HashMap<IpAddr, usize> = HashMap::new();
                    for (a, _) in &waiting {
                        *per_ip.entry(a.ip()).or_default() += 1;
                    }
                    let busiest = per_ip
                        .iter()
                        .max_by_key(|(ip, n)| (**n, **ip == peer.ip()))
                        .map(|(ip, _)| *ip);
                    let oldest = waiting
                        .iter()
                        .filter(|(a, _)| Some(a.ip()) == busiest)
                        .min_by_key(|(_, n)| *n)
                        .map(|(a, _)| *a);
                    if let Some((_, c)) = oldest.and_then(|a| conns.open.get(&a)) {
                        c.close();
                        self.closed.fetch_add(1, Ordering::Relaxed);
                    }
                }
            }
            conns.next += 1;
            let n = conns.next;
            conns.open.insert(peer, (n, Arc::clone(&conn)));
        }
        let deadline =
            (self.token.is_some()).then(|| Box::pin(tokio::time::sleep(self.limits.handshake)));
        GatedStream {
            inner: stream,
            peer,
            conn,
            gate: Arc::clone(self),
            deadline,
        }
    }

    fn forget(&self, peer: SocketAddr, conn: &Arc<Conn>) {
        let mut conns = self.conns.lock().unwrap_or_else(|p| p.into_inner());
        if conns
            .open
            .get(&peer)
            .is_some_and(|(_, c)| Arc::ptr_eq(c, conn))
        {
            conns.open.remove(&peer);
        }
    }

    /// Whether the request carries the token: in its headers, or for the
    /// studio's event stream, its `token` query parameter
    /// ([`crate::guard::admits`]).
    fn admits<B>(&self, request: &Request<B>) -> bool {
        let Some(token) = &self.token else {
            return true;
        };
        crate::guard::admits(request.method(), request.uri(), request.headers(), token)
    }

    /// Counts a refusal of `peer`; logs it when the peer's last line is a
    /// minute old, with the refusals since.
    fn refuse(&self, peer: Option<SocketAddr>, what: &str) {
        self.refused.fetch_add(1, Ordering::Relaxed);
        let ip = peer.map_or(IpAddr::from([0, 0, 0, 0]), |p| p.ip());
        let now = Instant::now();
        let mut refusals = self.refusals.lock().unwrap_or_else(|p| p.into_inner());
        if refusals.len() >= LOG_PEERS {
            refusals.retain(|_, r| now.duration_since(r.logged) < LOG_EVERY);
        }
        let known = refusals.len();
        let log = match refusals.get_mut(&ip) {
            Some(r) if now.duration_since(r.logged) < LOG_EVERY => {
                r.since += 1;
                None
            }
            Some(r) => {
                let since = r.since;
                *r = Refusals {
                    logged: now,
                    since: 0,
                };
                Some(since)
            }
            None if known < LOG_PEERS => {
                refusals.insert(
                    ip,
                    Refusals {
                        logged: now,
                        since: 0,
                    },
                );
                Some(0)
            }
            None => None,
        };
        if let Some(before) = log {
            let peer = peer.map_or_else(|| "an unknown address".into(), |p| p.to_string());
            if before == 0 {
                tracing::warn!(
                    "refused {what} from {peer}: missing or wrong token \
                     (further refusals of this address are counted and logged once a minute)"
                );
            } else {
                tracing::warn!(
                    "refused {what} from {peer}: missing or wrong token; \
                     {before} more refused from this address in the last minute"
                );
            }
        }
    }

    /// The accepted connections of `listener`, gated.
    pub fn incoming(
        self: &Arc<Gate>,
        listener: TcpListener,
    ) -> impl futures_util::Stream<Item = Result<GatedStream, std::io::Error>> + use<> {
        let gate = Arc::clone(self);
        futures_util::stream::unfold((gate, listener), |(gate, listener)| async move {
            loop {
                match listener.accept().await {
                    Ok((stream, _)) => {
                        // No Nagle: a tile's reply must not wait for a delayed ACK.
                        let _ = stream.set_nodelay(true);
                        let gated = gate.admit(stream);
                        return Some((Ok(gated), (gate, listener)));
                    }
                    Err(e) => {
                        // Out of file descriptors (or another passing error):
                        // wait a little rather than spin; closed connections
                        // free descriptors meanwhile.
                        tracing::debug!("accept: {e}");
                        tokio::time::sleep(Duration::from_millis(20)).await;
                    }
                }
            }
        })
    }
}

/// An accepted connection under the gate: reads and writes fail once the
/// gate closes it or its handshake time runs out unauthenticated.
pub struct GatedStream {
    inner: TcpStream,
    peer: Option<SocketAddr>,
    conn: Arc<Conn>,
    gate: Arc<Gate>,
    deadline: Option<Pin<Box<tokio::time::Sleep>>>,
}

impl GatedStream {
    fn check(&mut self, cx: &mut Context<'_>) -> Result<(), std::io::Error> {
        let closed = || {
            std::io::Error::new(
                std::io::ErrorKind::ConnectionAborted,
                "closed by the farm's gate: not authenticated",
            )
        };
        if self.conn.closed.load(Ordering::Acquire) {
            return Err(closed());
        }
        if self.conn.authenticated.load(Ordering::Acquire) {
            self.deadline = None;
            return Ok(());
        }
        *self.conn.waker.lock().unwrap_or_else(|p| p.into_inner()) = Some(cx.waker().clone());
        if let Some(deadline) = &mut self.deadline
            && deadline.as_mut().poll(cx).is_ready()
        {
            self.conn.closed.store(true, Ordering::Release);
            self.gate.closed.fetch_add(1, Ordering::Relaxed);
            return Err(closed());
        }
        Ok(())
    }
}

impl Drop for GatedStream {
    fn drop(&mut self) {
        if let Some(peer) = self.peer {
            self.gate.forget(peer, &self.conn);
        }
    }
}

impl AsyncRead for GatedStream {
    fn poll_read(
        mut self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        buf: &mut ReadBuf<'_>,
    ) -> Poll<std::io::Result<()>> {
        if let Err(e) = self.check(cx) {
            return Poll::Ready(Err(e));
        }
        Pin::new(&mut self.inner).poll_read(cx, buf)
    }
}

impl AsyncWrite for GatedStream {
    fn poll_write(
        mut self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        buf: &[u8],
    ) -> Poll<std::io::Result<usize>> {
        if self.conn.closed.load(Ordering::Acquire) {
            return Poll::Ready(Err(std::io::ErrorKind::ConnectionAborted.into()));
        }
        Pin::new(&mut self.inner).poll_write(cx, buf)
    }

    fn poll_flush(mut self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<std::io::Result<()>> {
        Pin::new(&mut self.inner).poll_flush(cx)
    }

    fn poll_shutdown(mut self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<std::io::Result<()>> {
        Pin::new(&mut self.inner).poll_shutdown(cx)
    }

    fn poll_write_vectored(
        mut self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        bufs: &[std::io::IoSlice<'_>],
    ) -> Poll<std::io::Result<usize>> {
        if self.conn.closed.load(Ordering::Acquire) {
            return Poll::Ready(Err(std::io::ErrorKind::ConnectionAborted.into()));
        }
        Pin::new(&mut self.inner).poll_write_vectored(cx, bufs)
    }

    fn is_write_vectored(&self) -> bool {
        self.inner.is_write_vectored()
    }
}

impl Connected for GatedStream {
    type ConnectInfo = TcpConnectInfo;

    fn connect_info(&self) -> TcpConnectInfo {
        self.inner.connect_info()
    }
}

/// The tower layer that refuses gRPC calls without the token from their
/// headers and marks a connection authenticated by its first request with it.
#[derive(Clone)]
pub struct GateLayer(pub Arc<Gate>);

impl<S> tower::Layer<S> for GateLayer {
    type Service = GateService<S>;

    fn layer(&self, inner: S) -> GateService<S> {
        GateService {
            gate: Arc::clone(&self.0),
            inner,
        }
    }
}

/// See [`GateLayer`].
#[derive(Clone)]
pub struct GateService<S> {
    gate: Arc<Gate>,
    inner: S,
}

/// The peer of a request, as tonic's server recorded it.
fn peer_of<B>(request: &Request<B>) -> Option<SocketAddr> {
    use tonic::transport::server::TlsConnectInfo;
    let extensions = request.extensions();
    extensions
        .get::<TcpConnectInfo>()
        .and_then(TcpConnectInfo::remote_addr)
        .or_else(|| {
            extensions
                .get::<TlsConnectInfo<TcpConnectInfo>>()?
                .get_ref()
                .remote_addr()
        })
}

/// Whether a request is a gRPC call (by its content type).
pub(crate) fn is_grpc<B>(request: &Request<B>) -> bool {
    request
        .headers()
        .get(axum::http::header::CONTENT_TYPE)
        .is_some_and(|v| v.as_bytes().starts_with(b"application/grpc"))
}

type BoxFuture<T, E> = Pin<Box<dyn Future<Output = Result<T, E>> + Send>>;

impl<S, B> tower::Service<Request<B>> for GateService<S>
where
    S: tower::Service<Request<B>, Response = Response<tonic::body::Body>>,
    S::Future: Send + 'static,
    S::Error: Send + 'static,
{
    type Response = Response<tonic::body::Body>;
    type Error = S::Error;
    type Future = BoxFuture<Self::Response, Self::Error>;

    fn poll_ready(&mut self, cx: &mut Context<'_>) -> Poll<Result<(), Self::Error>> {
        self.inner.poll_ready(cx)
    }

    fn call(&mut self, request: Request<B>) -> Self::Future {
        let peer = peer_of(&request);
        if let Err(refused) =
            self.gate
                .hosts
                .check(request.method(), request.uri(), request.headers())
        {
            tracing::debug!(
                "refused {} {} from {}: {}",
                request.method(),
                hypertexture_proto::convert::untrusted(request.uri().path(), 128),
                peer.map_or_else(|| "an unknown address".into(), |p| p.to_string()),
                refused.message
            );
            let response = if is_grpc(&request) {
                tonic::Status::permission_denied(refused.message).into_http()
            } else {
                json_error(refused.status, &refused.message)
            };
            return Box::pin(std::future::ready(Ok(response)));
        }
        if self.gate.admits(&request) {
            if let Some(peer) = peer {
                let conns = self.gate.conns.lock().unwrap_or_else(|p| p.into_inner());
                if let Some((_, c)) = conns.open.get(&peer) {
                    c.authenticated.store(true, Ordering::Release);
                }
            }
            return Box::pin(self.inner.call(request));
        }
        if is_grpc(&request) {
            let what = format!(
                "a call to {}",
                hypertexture_proto::convert::untrusted(request.uri().path(), 128)
            );
            self.gate.refuse(peer, &what);
            let status = tonic::Status::unauthenticated("missing or wrong token");
            return Box::pin(std::future::ready(Ok(status.into_http())));
        }
        // The HTTP routes answer a missing token themselves (401 with a JSON
        // body, or a public page); the connection stays unauthenticated.
        Box::pin(self.inner.call(request))
    }
}

/// An answer of `status` with the body `{"error": message}`.
pub(crate) fn json_error(
    status: axum::http::StatusCode,
    message: &str,
) -> Response<tonic::body::Body> {
    let body = serde_json::json!({ "error": message }).to_string();
    let mut response = Response::new(tonic::body::Body::new(axum::body::Body::from(body)));
    *response.status_mut() = status;
    response.headers_mut().insert(
        axum::http::header::CONTENT_TYPE,
        axum::http::HeaderValue::from_static("application/json"),
    );
    response
}

#[cfg(test)]
mod tests {
    use super::*;

    #[tokio::test]
    async fn refusals_are_logged_once_a_minute_a_peer_with_their_count() {
        let gate = Gate::new(Some("s3cret"), GateLimits::default(), &[]);
        let a: SocketAddr = "10.0.0.1:1".parse().unwrap();
        for _ in 0..5 {
            gate.refuse(Some(a), "a call");
        }
        assert_eq!(gate.refused(), 5);
        let r = gate.refusals.lock().unwrap();
        assert_eq!(r.len(), 1);
        assert_eq!(r[&a.ip()].since, 4, "the first is logged, four are counted");
    }

    #[test]
    fn the_token_is_read_from_the_header_or_the_query() {
        let gate = Gate::new(Some("s3cret"), GateLimits::default(), &[]);
        let with = |h: Option<&str>, uri: &str| {
            let mut r = Request::builder().uri(uri);
            if let Some(h) = h {
                r = r.header("authorization", h);
            }
            gate.admits(&r.body(()).unwrap())
        };
        assert!(with(Some("Bearer s3cret"), "/x"));
        assert!(with(Some("bearer s3cret"), "/x"));
        assert!(!with(Some("Bearer s3cre"), "/x"));
        assert!(!with(None, "/x"));
        assert!(with(Some("BEARER s3cret"), "/x"));
        assert!(with(None, "/studio/events?token=s3cret"));
        assert!(!with(None, "/studio/events?token=nope"));
        assert!(!with(None, "/studio/scene?token=s3cret"));
        assert!(!with(
            None,
            "/studio/tiles?generation=0&from=0&to=0&token=s3cret"
        ));
        assert!(Gate::new(None, GateLimits::default(), &[]).admits(&Request::new(())));
    }
}
