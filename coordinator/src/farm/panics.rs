//! Panics in the coordinator: a request's own panic fails that request; any
//! other fails the render.
//!
//! * **In a request's handler** (an HTTP route or a gRPC method, while its
//!   future or its answer's body is polled): [`CatchLayer`], the server's
//!   outermost layer, catches it. The request is answered 500 with a JSON
//!   error (a gRPC call: `INTERNAL`), or, when its answer had begun (an
//!   event stream, a gRPC stream), its body ends with an error. The panic
//!   is logged with the method and path, and counted
//!   (`hypertexture_handler_panics_total`); the service goes on.
//! * **Anywhere else** (a task of the farm's own, a preview writer): a hook
//!   records the first, and the farm's supervisor
//!   ([`crate::farm::Farm::tick`]) ends the render (or the service) with
//!   it, for a non-zero exit. Without it such a task would end alone, and
//!   the render would go on, or wait, on a state nobody can trust.
//! * **On a render thread**: the unit fails (a worker, the in-process ones
//!   included, catches it and reports the unit; the scheduler gives it to
//!   another).

use std::cell::{Cell, RefCell};
use std::future::Future;
use std::panic::AssertUnwindSafe;
use std::pin::Pin;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, OnceLock};
use std::task::{Context, Poll};

use axum::http::{Request, Response, StatusCode};
use hypertexture_proto::Bytes;

/// The first panic recorded outside a handler.
static FIRST: OnceLock<String> = OnceLock::new();

/// Handler panics caught so far.
static CAUGHT: AtomicU64 = AtomicU64::new(0);

thread_local! {
    /// Whether this thread is polling a request's handler (its panic is the
    /// request's, not the process's).
    static IN_HANDLER: Cell<bool> = const { Cell::new(false) };
    /// The last handler panic of this thread: its message and place.
    static MESSAGE: RefCell<Option<String>> = const { RefCell::new(None) };
}

/// Installs the hook (once per process). The previous hook still prints a
/// panic outside handlers; a handler's panic is logged by [`CatchLayer`].
pub fn install() {
    static INSTALLED: std::sync::Once = std::sync::Once::new();
    INSTALLED.call_once(|| {
        let previous = std::panic::take_hook();
        std::panic::set_hook(Box::new(move |info| {
            if IN_HANDLER.get() {
                let message = info.to_string().replace('\n', ": ");
                MESSAGE.set(Some(message));
                return;
            }
            let thread = std::thread::current();
            if counts(thread.name()) {
                let message = format!("panic on thread {}: {info}", thread.name().unwrap_or("?"));
                #[cfg(test)]
                tests::RECORDED
                    .lock()
                    .unwrap_or_else(|p| p.into_inner())
                    .push(message.clone());
                let _ = FIRST.set(message);
            }
            previous(info);
        }));
    });
}

/// Whether a panic on the thread named `name` is the coordinator's. A
/// render thread's is not: a worker (the in-process ones included) catches
/// it and reports the unit as failed, which the scheduler handles.
fn counts(name: Option<&str>) -> bool {
    !name.is_some_and(|n| n.starts_with("render-"))
}

/// The first panic recorded since [`install`] outside a handler, if any.
pub fn first() -> Option<&'static str> {
    FIRST.get().map(String::as_str)
}

/// Handler panics caught so far ([`CatchLayer`]).
pub fn caught() -> u64 {
    CAUGHT.load(Ordering::Relaxed)
}

/// Runs `f` as a request's handler code: a panic in it is returned, not
/// recorded as the process's.
fn in_handler<R>(f: impl FnOnce() -> R) -> std::thread::Result<R> {
    let outer = IN_HANDLER.replace(true);
    let result = std::panic::catch_unwind(AssertUnwindSafe(f));
    IN_HANDLER.set(outer);
    result
}

/// The request a handler served, for the log line and the answer.
struct Route {
    method: String,
    path: String,
    grpc: bool,
}

impl Route {
    fn of<B>(request: &Request<B>) -> Route {
        Route {
            method: request.method().to_string(),
            path: hypertexture_proto::convert::untrusted(request.uri().path(), 128),
            grpc: crate::farm::gate::is_grpc(request),
        }
    }

    /// Counts and logs the panic just caught on this thread.
    fn caught(&self, when: &str) {
        CAUGHT.fetch_add(1, Ordering::Relaxed);
        let message = MESSAGE
            .take()
            .unwrap_or_else(|| "a panic without a message".into());
        tracing::error!(
            "{} {}: the handler panicked {when} ({message}); this request failed, \
             the service goes on",
            self.method,
            self.path
        );
    }

    /// The answer to a request whose handler panicked.
    fn answer(&self) -> Response<tonic::body::Body> {
        if self.grpc {
            return tonic::Status::internal(
                "the coordinator failed on this call (a defect; it is in its log)",
            )
            .into_http();
        }
        crate::farm::gate::json_error(
            StatusCode::INTERNAL_SERVER_ERROR,
            &format!(
                "{} {}: the coordinator failed on this request (a defect; it is in its log)",
                self.method, self.path
            ),
        )
    }
}

/// The tower layer that turns a panic in a request's handler into that
/// request's failure (see the module's documentation).
#[derive(Clone, Copy, Debug, Default)]
pub struct CatchLayer;

impl<S> tower::Layer<S> for CatchLayer {
    type Service = Catch<S>;

    fn layer(&self, inner: S) -> Catch<S> {
        Catch { inner }
    }
}

/// See [`CatchLayer`].
#[derive(Clone, Debug)]
pub struct Catch<S> {
    inner: S,
}

impl<S, B> tower::Service<Request<B>> for Catch<S>
where
    S: tower::Service<Request<B>, Response = Response<tonic::body::Body>>,
{
    type Response = Response<tonic::body::Body>;
    type Error = S::Error;
    type Future = Caught<S::Future>;

    fn poll_ready(&mut self, cx: &mut Context<'_>) -> Poll<Result<(), Self::Error>> {
        self.inner.poll_ready(cx)
    }

    fn call(&mut self, request: Request<B>) -> Self::Future {
        let route = Arc::new(Route::of(&request));
        let inner = &mut self.inner;
        match in_handler(move || inner.call(request)) {
            Ok(future) => Caught {
                future: Some(Box::pin(future)),
                route,
            },
            Err(_) => {
                route.caught("before its answer");
                Caught {
                    future: None,
                    route,
                }
            }
        }
    }
}

/// The future of a [`Catch`]: the handler's, or its failure's answer.
pub struct Caught<F> {
    /// `None` once the handler panicked.
    future: Option<Pin<Box<F>>>,
    route: Arc<Route>,
}

impl<F, E> Future for Caught<F>
where
    F: Future<Output = Result<Response<tonic::body::Body>, E>>,
{
    type Output = F::Output;

    fn poll(mut self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<Self::Output> {
        let Some(future) = self.future.as_mut() else {
            return Poll::Ready(Ok(self.route.answer()));
        };
        match in_handler(|| future.as_mut().poll(cx)) {
            Ok(Poll::Ready(Ok(response))) => {
                let route = Arc::clone(&self.route);
                Poll::Ready(Ok(response.map(|inner| {
                    tonic::body::Body::new(CaughtBody {
                        inner,
                        route,
                        failed: false,
                    })
                })))
            }
            Ok(other) => other,
            Err(_) => {
                self.future = None;
                self.route.caught("before its answer");
                Poll::Ready(Ok(self.route.answer()))
            }
        }
    }
}

/// An answer's body whose handler code (an event stream, a gRPC stream)
/// may panic while it is polled: the body then ends with an error.
struct CaughtBody {
    inner: tonic::body::Body,
    route: Arc<Route>,
    failed: bool,
}

impl http_body::Body for CaughtBody {
    type Data = Bytes;
    type Error = tonic::Status;

    fn poll_frame(
        mut self: Pin<&mut Self>,
        cx: &mut Context<'_>,
    ) -> Poll<Option<Result<http_body::Frame<Bytes>, tonic::Status>>> {
        if self.failed {
            return Poll::Ready(None);
        }
        let inner = &mut self.inner;
        match in_handler(|| Pin::new(inner).poll_frame(cx)) {
            Ok(frame) => frame,
            Err(_) => {
                self.failed = true;
                self.route.caught("in its answer's body");
                Poll::Ready(Some(Err(tonic::Status::internal(
                    "the coordinator failed on this request (a defect; it is in its log)",
                ))))
            }
        }
    }

    fn is_end_stream(&self) -> bool {
        self.failed || self.inner.is_end_stream()
    }

    fn size_hint(&self) -> http_body::SizeHint {
        self.inner.size_hint()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use axum::http::header;
    use std::sync::Mutex;
    use tower::{Service, ServiceExt};

    /// Every panic the hook recorded as the process's.
    pub(super) static RECORDED: Mutex<Vec<String>> = Mutex::new(Vec::new());

    fn recorded(needle: &str) -> bool {
        RECORDED
            .lock()
            .unwrap_or_else(|p| p.into_inner())
            .iter()
            .any(|m| m.contains(needle))
    }

    #[test]
    fn a_panic_in_a_spawned_task_is_recorded_and_a_render_threads_is_not() {
        install();
        let render = std::thread::Builder::new()
            .name("render-0".into())
            .spawn(|| panic!("a unit's render"))
            .unwrap()
            .join();
        assert!(render.is_err());
        assert!(
            !recorded("a unit's render"),
            "a render thread's panic is a unit failure"
        );
        let runtime = tokio::runtime::Builder::new_current_thread()
            .build()
            .unwrap();
        let task = runtime.block_on(async { tokio::spawn(async { panic!("in a task") }).await });
        assert!(task.is_err());
        assert!(recorded("in a task"));
        assert!(first().is_some());
    }

    /// Routes that panic before their answer and in its body, and one that
    /// does not, behind the layer as the server stacks it.
    fn service() -> impl Service<
        Request<axum::body::Body>,
        Response = Response<tonic::body::Body>,
        Error = std::convert::Infallible,
    > {
        let router = axum::Router::new()
            .route(
                "/boom",
                axum::routing::get(|| async {
                    if std::hint::black_box(true) {
                        panic!("boom in a handler");
                    }
                    "never"
                })
                .post(|| async {
                    if std::hint::black_box(true) {
                        panic!("boom in a gRPC method");
                    }
                    "never"
                }),
            )
            .route(
                "/stream",
                axum::routing::get(|| async {
                    let chunks = futures_util::stream::unfold(0, |n| async move {
                        assert!(n < 1, "boom in a body");
                        Some((Ok::<_, std::io::Error>(Bytes::from_static(b"first")), n + 1))
                    });
                    axum::body::Body::from_stream(chunks)
                }),
            )
            .route("/ok", axum::routing::get(|| async { "ok" }));
        tower::ServiceBuilder::new()
            .layer(CatchLayer)
            .map_response(|r: Response<axum::body::Body>| r.map(tonic::body::Body::new))
            .service(router)
    }

    async fn call(method: &str, path: &str, grpc: bool) -> (Response<()>, Result<Bytes, String>) {
        let mut request = Request::builder().method(method).uri(path);
        if grpc {
            request = request.header(header::CONTENT_TYPE, "application/grpc");
        }
        let request = request.body(axum::body::Body::empty()).unwrap();
        let response = service().oneshot(request).await.unwrap();
        let (parts, body) = response.into_parts();
        let body = axum::body::to_bytes(axum::body::Body::new(body), 1 << 20)
            .await
            .map_err(|e| e.to_string());
        (Response::from_parts(parts, ()), body)
    }

    #[tokio::test]
    async fn a_handlers_panic_fails_its_request_alone() {
        install();
        let before = caught();
        let (response, body) = call("GET", "/boom", false).await;
        assert_eq!(response.status(), StatusCode::INTERNAL_SERVER_ERROR);
        assert_eq!(response.headers()[header::CONTENT_TYPE], "application/json");
        let error: serde_json::Value = serde_json::from_slice(&body.unwrap()).unwrap();
        assert!(
            error["error"].as_str().unwrap().contains("GET /boom"),
            "{error}"
        );

        let (response, _) = call("POST", "/boom", true).await;
        assert_eq!(response.status(), StatusCode::OK);
        assert_eq!(response.headers()["grpc-status"], "13");

        let (response, body) = call("GET", "/stream", false).await;
        assert_eq!(response.status(), StatusCode::OK);
        assert!(body.is_err(), "the body ends with an error");

        assert!(caught() >= before + 3);
        for message in [
            "boom in a handler",
            "boom in a gRPC method",
            "boom in a body",
        ] {
            assert!(!recorded(message), "{message}: not the process's panic");
        }
        // The service goes on.
        let (response, body) = call("GET", "/ok", false).await;
        assert_eq!(response.status(), StatusCode::OK);
        assert_eq!(&body.unwrap()[..], b"ok");
    }
}
