//! The HTTP/JSON API of `coordinator serve`: jobs, workers, metrics and the
//! OpenAPI document that describes them.
//!
//! [`router`] builds an [`axum::Router`] that binds no socket: the service
//! merges it with the workers' gRPC routes on one port. Its layers (the token
//! check, the body limit, the JSON error bodies) wrap only the routes defined
//! here, so routes added afterwards, such as `/hypertexture.v1.Farm/…`, are
//! served untouched. Paths without a route reach the fallback, which needs no
//! token: a JSON 404, or for a gRPC request the gRPC status UNIMPLEMENTED.
//!
//! With a token, every route (the API, the OpenAPI document, `/metrics`)
//! needs `Authorization: Bearer <token>`, checked from the headers before the
//! body is read; a refusal is 401 with `WWW-Authenticate: Bearer`, and is
//! logged at most once a minute for each peer address.
//!
//! | Method and path              | Success               | Refusals            |
//! |------------------------------|-----------------------|---------------------|
//! | `POST /api/v1/jobs`          | 201 [`JobView`]       | 400 401 403 413 415 429 503 |
//! | `GET /api/v1/jobs?limit&cursor` | 200 `[JobView]`, a page | 400 401          |
//! | `GET /api/v1/jobs/{id}`      | 200 [`JobView`]       | 400 401 404         |
//! | `POST /api/v1/jobs/{id}/cancel` | 200 [`JobView`]    | 400 401 404 409 503 |
//! | `GET /api/v1/workers`        | 200 `[WorkerView]`    | 401                 |
//! | `GET /api/v1/openapi.json`   | 200 the OpenAPI 3 document | 401            |
//! | `GET /metrics`               | 200 Prometheus text   | 401                 |
//!
//! `GET /api/v1/jobs` answers a page, newest first (`limit`, default
//! [`DEFAULT_PAGE`](crate::service::limits::DEFAULT_PAGE), at most
//! [`MAX_PAGE`](crate::service::limits::MAX_PAGE)); when more jobs follow, a
//! `Link: </api/v1/jobs?limit=N&cursor=C>; rel="next"` header names the next
//! page. A submission past `--max-queued` is 429 with `Retry-After`.
//!
//! Every answer of 400 or above is `{"error": "<one line>"}` with
//! `Content-Type: application/json`, axum's own refusals (bad JSON, a wrong
//! content type, an unknown path, a wrong method, a body over
//! [`MAX_BODY_BYTES`]) included.

use std::collections::HashMap;
use std::net::{IpAddr, SocketAddr};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use axum::Json;
use axum::Router;
use axum::body::Body;
use axum::extract::rejection::{JsonRejection, PathRejection};
use axum::extract::{DefaultBodyLimit, OriginalUri, Path, Request, State};
use axum::http::{HeaderMap, HeaderValue, Method, StatusCode, header};
use axum::middleware::{self, Next};
use axum::response::{IntoResponse, Response};
use serde::{Deserialize, Serialize};
use utoipa::openapi::security::{Http, HttpAuthScheme, SecurityScheme};
use utoipa::{Modify, OpenApi, ToSchema};
use utoipa_axum::router::OpenApiRouter;
use utoipa_axum::routes;

use crate::service::jobs::{ApiError, Control, JobSpec, JobView, WorkerView};

/// The largest request body accepted (256 KiB); larger ones get 413.
pub const MAX_BODY_BYTES: usize = 256 * 1024;

/// The path of the OpenAPI document.
pub const OPENAPI_PATH: &str = "/api/v1/openapi.json";

/// The content type of `/metrics` (the Prometheus text exposition format).
pub const METRICS_CONTENT_TYPE: &str = "text/plain; version=0.0.4";

/// Refusals of one peer address logged at most this often.
const WARN_EVERY: Duration = Duration::from_secs(60);

/// Peer addresses remembered for throttling before old entries are dropped.
const WARN_PEERS: usize = 4096;

/// The body of every answer of status 400 or above.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize, ToSchema)]
pub struct ErrorBody {
    /// What was wrong, on one line.
    pub error: String,
}

/// A refusal: an HTTP status and a one-line message, answered as [`ErrorBody`].
#[derive(Clone, Debug, PartialEq)]
pub struct Refusal {
    /// The status.
    pub status: StatusCode,
    /// The message.
    pub message: String,
}

impl Refusal {
    /// A refusal with `status` and `message` (cut to its first line).
    pub fn new(status: StatusCode, message: impl Into<String>) -> Refusal {
        Refusal {
            status,
            message: one_line(&message.into()),
        }
    }
}

impl From<ApiError> for Refusal {
    fn from(e: ApiError) -> Refusal {
        let status = match e {
            ApiError::BadRequest(_) => StatusCode::BAD_REQUEST,
            ApiError::Forbidden(_) => StatusCode::FORBIDDEN,
            ApiError::TooMany(_) => StatusCode::TOO_MANY_REQUESTS,
            ApiError::NotFound(_) => StatusCode::NOT_FOUND,
            ApiError::Conflict(_) => StatusCode::CONFLICT,
            ApiError::Unavailable(_) => StatusCode::SERVICE_UNAVAILABLE,
            ApiError::Internal(_) => StatusCode::INTERNAL_SERVER_ERROR,
            ApiError::InsufficientStorage(_) => StatusCode::INSUFFICIENT_STORAGE,
        };
        Refusal::new(status, e.to_string())
    }
}

impl From<JsonRejection> for Refusal {
    fn from(r: JsonRejection) -> Refusal {
        // A body that is not JSON, or JSON that is not a job, is the client's
        // malformed request: 400 (axum says 422 for the latter).
        let status = match &r {
            JsonRejection::JsonDataError(_) | JsonRejection::JsonSyntaxError(_) => {
                StatusCode::BAD_REQUEST
            }
            other => other.status(),
        };
        Refusal::new(status, r.body_text())
    }
}

impl From<PathRejection> for Refusal {
    fn from(r: PathRejection) -> Refusal {
        Refusal::new(StatusCode::BAD_REQUEST, r.body_text())
    }
}

impl IntoResponse for Refusal {
    fn into_response(self) -> Response {
        if self.status.is_server_error() {
            tracing::error!("api: {}", self.message);
        }
        let status = self.status;
        let mut response = error_response(status, self.message);
        if status == StatusCode::TOO_MANY_REQUESTS {
            response.headers_mut().insert(
                header::RETRY_AFTER,
                HeaderValue::from(crate::service::limits::RETRY_AFTER_SECS),
            );
        }
        response
    }
}

/// `{"error": message}` with `status`.
fn error_response(status: StatusCode, message: String) -> Response {
    (status, Json(ErrorBody { error: message })).into_response()
}

/// The first non-empty line of `s`, trimmed (at most 1000 characters).
fn one_line(s: &str) -> String {
    let line = s
        .lines()
        .map(str::trim)
        .find(|l| !l.is_empty())
        .unwrap_or("");
    match line.char_indices().nth(1000) {
        Some((cut, _)) => format!("{}…", &line[..cut]),
        None => line.to_string(),
    }
}

/// The OpenAPI document's fixed parts; the paths come from the handlers.
#[derive(OpenApi)]
#[openapi(
    info(
        title = "hypertexture coordinator",
        description = "The job queue of `coordinator serve`: submit scenes to render on the farm, \
                       follow and cancel them, list the workers. Every refusal is \
                       `{\"error\": \"…\"}`. When the service has a token, every request \
                       carries `Authorization: Bearer <token>`."
    ),
    components(schemas(ErrorBody)),
    modifiers(&BearerScheme),
    security((), ("bearer" = []))
)]
struct ApiDoc;

/// Adds the `bearer` security scheme and the quality preset's schema.
struct BearerScheme;

impl Modify for BearerScheme {
    fn modify(&self, openapi: &mut utoipa::openapi::OpenApi) {
        let components = openapi.components.get_or_insert_with(Default::default);
        components.add_security_scheme(
            "bearer",
            SecurityScheme::Http(Http::new(HttpAuthScheme::Bearer)),
        );
        // The library's `Quality`, which the job's `quality` field names.
        components.schemas.insert(
            crate::service::jobs::QUALITY_SCHEMA.into(),
            crate::service::jobs::quality_schema().into(),
        );
    }
}

/// The API on `control`; with `token`, every request must carry
/// `Authorization: Bearer <token>` (checked before the body is read).
pub fn router(control: Arc<dyn Control>, token: Option<String>) -> Router {
    let (routes, doc) = api_routes().split_for_parts();
    let doc = Arc::new(doc);
    let auth = Arc::new(Auth {
        token: token.map(String::into_bytes),
        warned: Mutex::new(HashMap::new()),
    });
    routes
        .route(
            OPENAPI_PATH,
            axum::routing::get(move || {
                let doc = utoipa::openapi::OpenApi::clone(&doc);
                async move { Json(doc) }
            }),
        )
        .layer(DefaultBodyLimit::max(MAX_BODY_BYTES))
        .layer(middleware::from_fn_with_state(auth, check_token))
        .layer(middleware::from_fn(json_errors))
        // Set after the layers, so not wrapped by them: an unknown path has
        // nothing to protect, and a gRPC call to an unknown method gets a
        // gRPC answer rather than a JSON 401 or 404.
        .fallback(unknown_path)
        .with_state(control)
}

/// The OpenAPI document of [`router`].
pub fn openapi() -> utoipa::openapi::OpenApi {
    api_routes().into_openapi()
}

/// The documented routes and their document, from the same declarations.
fn api_routes() -> OpenApiRouter<Arc<dyn Control>> {
    OpenApiRouter::with_openapi(ApiDoc::openapi())
        .routes(routes!(submit_job, list_jobs))
        .routes(routes!(get_job))
        .routes(routes!(cancel_job))
        .routes(routes!(list_workers))
        .routes(routes!(metrics))
        .routes(routes!(readyz))
}

/// Whether the service is ready to take work.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize, ToSchema)]
pub struct Ready {
    /// Always true in a 200 answer.
    pub ready: bool,
}

/// The readiness probe: 200 while the service takes jobs and tiles; 503 with
/// the reason while its store cannot write (disk full, I/O error) or it is
/// shutting down. It turns ready again by itself when the store writes.
#[utoipa::path(
    get,
    path = "/readyz",
    tag = "metrics",
    responses(
        (status = 200, description = "Ready", body = Ready),
        (status = 401, description = "Missing or wrong bearer token", body = ErrorBody),
        (status = 503, description = "Not ready: the store cannot write, or the coordinator is draining", body = ErrorBody),
    )
)]
async fn readyz(State(control): State<Arc<dyn Control>>) -> Response {
    match control.ready() {
        Ok(()) => Json(Ready { ready: true }).into_response(),
        // Not logged: a probe asks every few seconds, and the service logs
        // the store's failure itself.
        Err(why) => error_response(StatusCode::SERVICE_UNAVAILABLE, one_line(&why)),
    }
}

/// Queues a job.
#[utoipa::path(
    post,
    path = "/api/v1/jobs",
    tag = "jobs",
    request_body = crate::service::jobs::JobJson,
    responses(
        (status = 201, description = "Queued", body = JobView,
            headers(("Location" = String, description = "The job's URL: /api/v1/jobs/{id}"))),
        (status = 400, description = "Malformed JSON, or a scene or setting the coordinator refuses (an output pattern's # run over 9, a path over PATH_MAX or a name over NAME_MAX)", body = ErrorBody),
        (status = 401, description = "Missing or wrong bearer token", body = ErrorBody),
        (status = 403, description = "The output is outside the service's output roots (--output-root), which the message names", body = ErrorBody),
        (status = 413, description = "Body over 256 KiB, or scene text over 64 KiB", body = ErrorBody),
        (status = 415, description = "Content-Type is not application/json", body = ErrorBody),
        (status = 429, description = "The queue holds --max-queued jobs not ended", body = ErrorBody,
            headers(("Retry-After" = u64, description = "Seconds to wait before submitting again"))),
        (status = 503, description = "The coordinator is draining, or its store cannot write (not queued, no id)", body = ErrorBody),
        (status = 507, description = "The store's disk is full: the job is not queued and has no id", body = ErrorBody),
    )
)]
async fn submit_job(
    State(control): State<Arc<dyn Control>>,
    body: Result<Json<JobSpec>, JsonRejection>,
) -> Result<Response, Refusal> {
    let Json(spec) = body?;
    let max = hypertexture::scene::MAX_SCENE_BYTES;
    if spec.request.scene_text.len() > max {
        return Err(Refusal::new(
            StatusCode::PAYLOAD_TOO_LARGE,
            format!(
                "{}: the scene text is {} bytes; the cap is {} bytes ({} KiB)",
                spec.request.scene_name,
                spec.request.scene_text.len(),
                max,
                max / 1024
            ),
        ));
    }
    let job = control.submit(spec)?;
    let location = format!("/api/v1/jobs/{}", job.id);
    let mut response = (StatusCode::CREATED, Json(job)).into_response();
    if let Ok(value) = HeaderValue::from_str(&location) {
        response.headers_mut().insert(header::LOCATION, value);
    }
    Ok(response)
}

/// A page of `GET /api/v1/jobs`.
#[derive(Debug, Deserialize, utoipa::IntoParams)]
#[into_params(parameter_in = Query)]
struct PageQuery {
    /// Jobs in the page: 1 to 1000, default 100.
    limit: Option<usize>,
    /// Where the page starts: the `cursor` of the previous page's `Link` header
    /// (absent: the newest job).
    cursor: Option<u64>,
}

/// The jobs, newest first, a page at a time.
#[utoipa::path(
    get,
    path = "/api/v1/jobs",
    tag = "jobs",
    params(PageQuery),
    responses(
        (status = 200, description = "A page of jobs, newest first", body = Vec<JobView>,
            headers(("Link" = String, description = "When more jobs follow: `</api/v1/jobs?limit=N&cursor=C>; rel=\"next\"`, the next page"))),
        (status = 400, description = "A limit or cursor that is not a number, or a limit outside 1 to 1000", body = ErrorBody),
        (status = 401, description = "Missing or wrong bearer token", body = ErrorBody),
    )
)]
async fn list_jobs(
    State(control): State<Arc<dyn Control>>,
    query: Result<axum::extract::Query<PageQuery>, axum::extract::rejection::QueryRejection>,
) -> Result<Response, Refusal> {
    use crate::service::limits::{DEFAULT_PAGE, MAX_PAGE};
    let axum::extract::Query(query) =
        query.map_err(|e| Refusal::new(StatusCode::BAD_REQUEST, e.body_text()))?;
    let limit = query.limit.unwrap_or(DEFAULT_PAGE);
    if !(1..=MAX_PAGE).contains(&limit) {
        return Err(Refusal::new(
            StatusCode::BAD_REQUEST,
            format!("limit {limit}: a page holds 1 to {MAX_PAGE} jobs"),
        ));
    }
    let (page, next) = control.jobs_page(query.cursor, limit);
    let mut response = Json(page).into_response();
    if let Some(next) = next
        && let Ok(link) = HeaderValue::from_str(&format!(
            "</api/v1/jobs?limit={limit}&cursor={next}>; rel=\"next\""
        ))
    {
        response.headers_mut().insert(header::LINK, link);
    }
    Ok(response)
}

/// One job.
#[utoipa::path(
    get,
    path = "/api/v1/jobs/{id}",
    tag = "jobs",
    params(("id" = u64, Path, description = "The job's id")),
    responses(
        (status = 200, description = "The job", body = JobView),
        (status = 400, description = "The id is not a number", body = ErrorBody),
        (status = 401, description = "Missing or wrong bearer token", body = ErrorBody),
        (status = 404, description = "No such job", body = ErrorBody),
    )
)]
async fn get_job(
    State(control): State<Arc<dyn Control>>,
    id: Result<Path<u64>, PathRejection>,
) -> Result<Json<JobView>, Refusal> {
    let Path(id) = id?;
    Ok(Json(control.job(id)?))
}

/// Cancels a job that has not ended.
#[utoipa::path(
    post,
    path = "/api/v1/jobs/{id}/cancel",
    tag = "jobs",
    params(("id" = u64, Path, description = "The job's id")),
    responses(
        (status = 200, description = "The job, cancelled", body = JobView),
        (status = 400, description = "The id is not a number", body = ErrorBody),
        (status = 401, description = "Missing or wrong bearer token", body = ErrorBody),
        (status = 404, description = "No such job", body = ErrorBody),
        (status = 409, description = "The job has already ended", body = ErrorBody),
        (status = 503, description = "The coordinator cannot take the request now (its store cannot write: the job goes on)", body = ErrorBody),
        (status = 507, description = "The store's disk is full: the cancel is not kept and the job goes on", body = ErrorBody),
    )
)]
async fn cancel_job(
    State(control): State<Arc<dyn Control>>,
    id: Result<Path<u64>, PathRejection>,
) -> Result<Json<JobView>, Refusal> {
    let Path(id) = id?;
    Ok(Json(control.cancel(id)?))
}

/// Every connected worker.
#[utoipa::path(
    get,
    path = "/api/v1/workers",
    tag = "workers",
    responses(
        (status = 200, description = "Every connected worker", body = Vec<WorkerView>),
        (status = 401, description = "Missing or wrong bearer token", body = ErrorBody),
    )
)]
async fn list_workers(State(control): State<Arc<dyn Control>>) -> Json<Vec<WorkerView>> {
    Json(control.workers())
}

/// The farm's metrics in the Prometheus text exposition format.
#[utoipa::path(
    get,
    path = "/metrics",
    tag = "metrics",
    responses(
        (status = 200, description = "Prometheus text exposition format 0.0.4",
            body = String, content_type = "text/plain; version=0.0.4"),
        (status = 401, description = "Missing or wrong bearer token", body = ErrorBody),
    )
)]
async fn metrics(State(control): State<Arc<dyn Control>>) -> Response {
    (
        [(header::CONTENT_TYPE, METRICS_CONTENT_TYPE)],
        control.metrics(),
    )
        .into_response()
}

/// The answer for every path without a route: a JSON 404, or for a gRPC
/// request (`Content-Type: application/grpc…`) the gRPC status UNIMPLEMENTED.
async fn unknown_path(
    method: Method,
    OriginalUri(uri): OriginalUri,
    headers: HeaderMap,
) -> Response {
    let grpc = headers
        .get(header::CONTENT_TYPE)
        .and_then(|v| v.to_str().ok())
        .is_some_and(|v| v.starts_with("application/grpc"));
    if grpc {
        return tonic::Status::unimplemented(format!("no gRPC method {}", uri.path()))
            .into_http::<Body>();
    }
    Refusal::new(
        StatusCode::NOT_FOUND,
        format!("no such resource: {method} {}", uri.path()),
    )
    .into_response()
}

/// The token check's state.
struct Auth {
    /// The token's bytes; `None`: no check.
    token: Option<Vec<u8>>,
    /// When each peer's last refusal was logged.
    warned: Mutex<HashMap<IpAddr, Instant>>,
}

impl Auth {
    /// Whether `headers` carry `Authorization: Bearer <token>` (compared in
    /// constant time).
    fn admits(&self, headers: &HeaderMap) -> bool {
        let Some(token) = &self.token else {
            return true;
        };
        crate::guard::bearer_is(
            headers.get(header::AUTHORIZATION).map(|v| v.as_bytes()),
            token,
        )
    }

    /// Whether a refusal of `peer` is to be logged now (once a minute a peer).
    fn warn_now(&self, peer: IpAddr) -> bool {
        let Ok(mut warned) = self.warned.lock() else {
            return false;
        };
        let now = Instant::now();
        if warned.len() >= WARN_PEERS {
            warned.retain(|_, at| now.duration_since(*at) < WARN_EVERY);
        }
        match warned.get(&peer) {
            Some(at) if now.duration_since(*at) < WARN_EVERY => false,
            _ if warned.len() >= WARN_PEERS => false,
            _ => {
                warned.insert(peer, now);
                true
            }
        }
    }
}

/// The peer's address, as the server that accepted the connection recorded it.
fn peer_address(request: &Request) -> Option<SocketAddr> {
    use tonic::transport::server::{TcpConnectInfo, TlsConnectInfo};
    let extensions = request.extensions();
    extensions
        .get::<axum::extract::ConnectInfo<SocketAddr>>()
        .map(|c| c.0)
        .or_else(|| extensions.get::<TcpConnectInfo>()?.remote_addr())
        .or_else(|| {
            extensions
                .get::<TlsConnectInfo<TcpConnectInfo>>()?
                .get_ref()
                .remote_addr()
        })
}

/// Refuses a request without the token (401), before any extractor reads its body.
async fn check_token(State(auth): State<Arc<Auth>>, request: Request, next: Next) -> Response {
    if auth.admits(request.headers()) {
        return next.run(request).await;
    }
    let peer = peer_address(&request);
    if auth.warn_now(peer.map_or(IpAddr::from([0, 0, 0, 0]), |p| p.ip())) {
        tracing::warn!(
            "api: refused {} {} from {}: missing or wrong bearer token (further refusals of this address are not logged for a minute)",
            request.method(),
            hypertexture_proto::convert::untrusted(request.uri().path(), 256),
            peer.map_or_else(|| "an unknown address".to_string(), |p| p.to_string())
        );
    }
    let mut response = error_response(
        StatusCode::UNAUTHORIZED,
        "missing or wrong bearer token: send `Authorization: Bearer <token>`".into(),
    );
    response
        .headers_mut()
        .insert(header::WWW_AUTHENTICATE, HeaderValue::from_static("Bearer"));
    response
}

/// Whether `headers` say the body is JSON.
fn is_json(headers: &HeaderMap) -> bool {
    headers
        .get(header::CONTENT_TYPE)
        .and_then(|v| v.to_str().ok())
        .is_some_and(|v| v.starts_with("application/json"))
}

/// Rewrites every answer of 400 or above that is not JSON yet (axum's own:
/// 405, a body over the limit, …) as [`ErrorBody`], keeping its headers.
pub(crate) async fn json_errors(request: Request, next: Next) -> Response {
    let method = request.method().clone();
    let path = request.uri().path().to_string();
    let response = next.run(request).await;
    let status = response.status();
    if status.as_u16() < 400 || is_json(response.headers()) {
        return response;
    }
    let (mut parts, body) = response.into_parts();
    let text = axum::body::to_bytes(body, 16 * 1024)
        .await
        .map(|b| one_line(&String::from_utf8_lossy(&b)))
        .unwrap_or_default();
    let reason = status
        .canonical_reason()
        .map_or_else(|| format!("HTTP {}", status.as_u16()), str::to_lowercase);
    let message = if !text.is_empty() {
        text
    } else if status == StatusCode::METHOD_NOT_ALLOWED {
        let allowed = parts
            .headers
            .get(header::ALLOW)
            .and_then(|v| v.to_str().ok())
            .unwrap_or("")
            .to_string();
        format!("{method} {path}: {reason}; allowed: {allowed}")
    } else {
        format!("{method} {path}: {reason}")
    };
    parts.headers.remove(header::CONTENT_LENGTH);
    parts.headers.insert(
        header::CONTENT_TYPE,
        HeaderValue::from_static("application/json"),
    );
    let body = serde_json::to_vec(&ErrorBody { error: message }).unwrap_or_default();
    Response::from_parts(parts, Body::from(body))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::service::jobs::JobState;
    use axum::body::Bytes;
    use proptest::prelude::*;
    use std::collections::BTreeSet;
    use tower::ServiceExt;

    /// A fake farm: jobs in a vector; a scene containing `bad` is refused.
    #[derive(Default)]
    pub(crate) struct Fake {
        pub(crate) jobs: Mutex<Vec<JobView>>,
        pub(crate) draining: bool,
    }

    pub(crate) fn view(id: u64, spec: &JobSpec) -> JobView {
        let frames = spec.request.frames.len() as u32;
        JobView {
            id,
            state: JobState::Queued,
            priority: spec.priority,
            scene_name: spec.request.scene_name.clone(),
            out: spec.out.clone(),
            frames_done: 0,
            frames_total: frames,
            units_done: 0,
            units_total: u64::from(frames) * 64,
            eta_seconds: None,
            error: None,
            outputs: Vec::new(),
            require_tags: spec.require_tags.clone(),
            blocklisted: Vec::new(),
        }
    }

    impl Control for Fake {
        fn submit(&self, spec: JobSpec) -> Result<JobView, ApiError> {
            if self.draining {
                return Err(ApiError::Unavailable("draining: no new jobs".into()));
            }
            if spec.request.scene_text.contains("bad") {
                return Err(ApiError::BadRequest(
                    "scene.ron:3:7: expected `)` found `(`".into(),
                ));
            }
            let mut jobs = self.jobs.lock().unwrap();
            let job = view(jobs.len() as u64 + 1, &spec);
            jobs.push(job.clone());
            Ok(job)
        }
        fn jobs(&self) -> Vec<JobView> {
            self.jobs.lock().unwrap().iter().rev().cloned().collect()
        }
        fn job(&self, id: u64) -> Result<JobView, ApiError> {
            let jobs = self.jobs.lock().unwrap();
            jobs.iter()
                .find(|j| j.id == id)
                .cloned()
                .ok_or(ApiError::NotFound(id))
        }
        fn cancel(&self, id: u64) -> Result<JobView, ApiError> {
            let mut jobs = self.jobs.lock().unwrap();
            let job = jobs
                .iter_mut()
                .find(|j| j.id == id)
                .ok_or(ApiError::NotFound(id))?;
            if job.state.is_final() {
                return Err(ApiError::Conflict(format!(
                    "job {id} has already ended ({})",
                    job.state.as_str()
                )));
            }
            job.state = JobState::Cancelled;
            Ok(job.clone())
        }
        fn workers(&self) -> Vec<WorkerView> {
            vec![WorkerView {
                id: "w1".into(),
                name: "box".into(),
                tags: vec!["gpu".into()],
                threads: 4,
                pixels_per_second: 12345.0,
                current_job: None,
                units: 3,
                blocklisted_for: Vec::new(),
            }]
        }
        fn metrics(&self) -> String {
            "hypertexture_jobs{state=\"queued\"} 0\n".into()
        }
    }

    fn spec_json(scene: &str) -> String {
        serde_json::json!({"scene": scene, "out": "/tmp/out.png"}).to_string()
    }

    fn app(token: Option<&str>) -> (Arc<Fake>, Router) {
        let fake = Arc::new(Fake::default());
        let router = router(fake.clone(), token.map(str::to_string));
        (fake, router)
    }

    async fn call(
        router: &Router,
        request: axum::http::Request<Body>,
    ) -> (StatusCode, HeaderMap, Bytes) {
        let response = router.clone().oneshot(request).await.unwrap();
        let status = response.status();
        let headers = response.headers().clone();
        let body = axum::body::to_bytes(response.into_body(), usize::MAX)
            .await
            .unwrap();
        (status, headers, body)
    }

    fn post_json(path: &str, body: impl Into<Body>) -> axum::http::Request<Body> {
        axum::http::Request::post(path)
            .header(header::CONTENT_TYPE, "application/json")
            .body(body.into())
            .unwrap()
    }

    fn get(path: &str) -> axum::http::Request<Body> {
        axum::http::Request::get(path).body(Body::empty()).unwrap()
    }

    /// The `error` of a JSON error body (panics when it is not one).
    fn error_of(headers: &HeaderMap, body: &[u8]) -> String {
        assert!(is_json(headers), "not JSON: {headers:?}");
        let e: ErrorBody = serde_json::from_slice(body).unwrap();
        assert!(!e.error.is_empty() && !e.error.contains('\n'), "{e:?}");
        e.error
    }

    #[tokio::test]
    async fn submit_answers_201_with_the_job_and_its_location() {
        let (fake, router) = app(None);
        let (status, headers, body) =
            call(&router, post_json("/api/v1/jobs", spec_json("Scene()"))).await;
        assert_eq!(status, StatusCode::CREATED);
        assert_eq!(headers[header::LOCATION], "/api/v1/jobs/1");
        let job: JobView = serde_json::from_slice(&body).unwrap();
        assert_eq!(job.id, 1);
        assert_eq!(job.out, "/tmp/out.png");
        assert_eq!(fake.jobs.lock().unwrap().len(), 1);

        let (status, _, body) = call(&router, get("/api/v1/jobs/1")).await;
        assert_eq!(status, StatusCode::OK);
        assert_eq!(serde_json::from_slice::<JobView>(&body).unwrap(), job);
        let (status, _, body) = call(&router, get("/api/v1/jobs")).await;
        assert_eq!(status, StatusCode::OK);
        assert_eq!(
            serde_json::from_slice::<Vec<JobView>>(&body).unwrap(),
            vec![job]
        );
        let (status, _, body) = call(&router, get("/api/v1/workers")).await;
        assert_eq!(status, StatusCode::OK);
        assert_eq!(
            serde_json::from_slice::<Vec<WorkerView>>(&body).unwrap()[0].name,
            "box"
        );
    }

    #[tokio::test]
    async fn malformed_json_and_wrong_types_are_400_with_serde_position() {
        let (fake, router) = app(None);
        let (status, headers, body) =
            call(&router, post_json("/api/v1/jobs", "{\"scene\": ")).await;
        assert_eq!(status, StatusCode::BAD_REQUEST);
        let e = error_of(&headers, &body);
        assert!(e.contains("line 1 column"), "{e}");

        let (status, headers, body) = call(
            &router,
            post_json("/api/v1/jobs", "{\"scene\": 5, \"out\": \"x.png\"}"),
        )
        .await;
        assert_eq!(status, StatusCode::BAD_REQUEST);
        let e = error_of(&headers, &body);
        assert!(e.contains("scene") && e.contains("line 1 column"), "{e}");

        let (status, headers, body) = call(
            &router,
            post_json(
                "/api/v1/jobs",
                "{\"scene\": \"\", \"out\": \"x.png\", \"colour\": 1}",
            ),
        )
        .await;
        assert_eq!(status, StatusCode::BAD_REQUEST);
        assert!(error_of(&headers, &body).contains("colour"));
        assert!(fake.jobs.lock().unwrap().is_empty());
    }

    #[tokio::test]
    async fn the_controls_bad_request_passes_verbatim() {
        let (_, router) = app(None);
        let (status, headers, body) =
            call(&router, post_json("/api/v1/jobs", spec_json("bad"))).await;
        assert_eq!(status, StatusCode::BAD_REQUEST);
        assert_eq!(
            error_of(&headers, &body),
            "scene.ron:3:7: expected `)` found `(`"
        );
    }

    #[tokio::test]
    async fn draining_is_503() {
        let fake = Arc::new(Fake {
            draining: true,
            ..Fake::default()
        });
        let router = router(fake, None);
        let (status, headers, body) =
            call(&router, post_json("/api/v1/jobs", spec_json("x"))).await;
        assert_eq!(status, StatusCode::SERVICE_UNAVAILABLE);
        assert!(error_of(&headers, &body).contains("draining"));
    }

    #[tokio::test]
    async fn a_wrong_content_type_is_415() {
        let (_, router) = app(None);
        for content_type in [None, Some("text/plain")] {
            let mut request = axum::http::Request::post("/api/v1/jobs");
            if let Some(c) = content_type {
                request = request.header(header::CONTENT_TYPE, c);
            }
            let request = request.body(Body::from(spec_json("x"))).unwrap();
            let (status, headers, body) = call(&router, request).await;
            assert_eq!(status, StatusCode::UNSUPPORTED_MEDIA_TYPE);
            assert!(error_of(&headers, &body).contains("application/json"));
        }
    }

    #[tokio::test]
    async fn the_token_is_required_when_set() {
        let (fake, router) = app(Some("s3cret"));
        let paths = ["/api/v1/jobs", "/api/v1/workers", "/metrics", OPENAPI_PATH];
        for path in paths {
            for auth in [
                None,
                Some("Bearer wrong"),
                Some("Bearer s3cre"),
                Some("Basic s3cret"),
                Some("s3cret"),
            ] {
                let mut request = axum::http::Request::get(path);
                if let Some(a) = auth {
                    request = request.header(header::AUTHORIZATION, a);
                }
                let (status, headers, body) =
                    call(&router, request.body(Body::empty()).unwrap()).await;
                assert_eq!(status, StatusCode::UNAUTHORIZED, "{path} {auth:?}");
                assert_eq!(headers[header::WWW_AUTHENTICATE], "Bearer");
                assert!(error_of(&headers, &body).contains("token"));
            }
        }
        // Refused before the body is read: an oversized body still gets 401.
        let big = vec![b'x'; 2 * MAX_BODY_BYTES];
        let (status, _, _) = call(&router, post_json("/api/v1/jobs", big)).await;
        assert_eq!(status, StatusCode::UNAUTHORIZED);
        let request = axum::http::Request::post("/api/v1/jobs")
            .header(header::CONTENT_TYPE, "application/json")
            .header(header::AUTHORIZATION, "Bearer wrong")
            .body(Body::from(spec_json("x")))
            .unwrap();
        assert_eq!(call(&router, request).await.0, StatusCode::UNAUTHORIZED);
        assert!(fake.jobs.lock().unwrap().is_empty());

        for (path, want) in [
            ("/api/v1/jobs", StatusCode::OK),
            ("/api/v1/workers", StatusCode::OK),
            ("/metrics", StatusCode::OK),
            (OPENAPI_PATH, StatusCode::OK),
            ("/nowhere", StatusCode::NOT_FOUND),
        ] {
            let request = axum::http::Request::get(path)
                .header(header::AUTHORIZATION, "Bearer s3cret")
                .body(Body::empty())
                .unwrap();
            assert_eq!(call(&router, request).await.0, want, "{path}");
        }
        let request = axum::http::Request::post("/api/v1/jobs")
            .header(header::CONTENT_TYPE, "application/json")
            .header(header::AUTHORIZATION, "bearer s3cret")
            .body(Body::from(spec_json("x")))
            .unwrap();
        assert_eq!(call(&router, request).await.0, StatusCode::CREATED);
    }

    #[test]
    fn refusals_of_a_peer_are_logged_once_a_minute() {
        let auth = Auth {
            token: None,
            warned: Mutex::new(HashMap::new()),
        };
        let a = IpAddr::from([10, 0, 0, 1]);
        let b = IpAddr::from([10, 0, 0, 2]);
        assert!(auth.warn_now(a));
        assert!(!auth.warn_now(a));
        assert!(auth.warn_now(b));
        assert!(!auth.warn_now(b));
    }

    #[tokio::test]
    async fn unknown_jobs_and_paths_are_404_json() {
        let (_, router) = app(None);
        let (status, headers, body) = call(&router, get("/api/v1/jobs/42")).await;
        assert_eq!(status, StatusCode::NOT_FOUND);
        assert_eq!(error_of(&headers, &body), "no job 42");
        let (status, headers, body) = call(&router, post_json("/api/v1/jobs/42/cancel", "")).await;
        assert_eq!(status, StatusCode::NOT_FOUND);
        assert_eq!(error_of(&headers, &body), "no job 42");
        for path in [
            "/",
            "/api/v1",
            "/api/v2/jobs",
            "/api/v1/jobs/1/frames",
            "/hypertexture.v1.Farm/Work",
        ] {
            let (status, headers, body) = call(&router, get(path)).await;
            assert_eq!(status, StatusCode::NOT_FOUND, "{path}");
            assert!(error_of(&headers, &body).contains(path));
        }
        let (status, headers, body) = call(&router, get("/api/v1/jobs/seven")).await;
        assert_eq!(status, StatusCode::BAD_REQUEST);
        assert!(error_of(&headers, &body).contains("seven"));
        let (status, headers, body) = call(&router, get("/api/v1/jobs/18446744073709551616")).await;
        assert_eq!(status, StatusCode::BAD_REQUEST);
        error_of(&headers, &body);
    }

    #[tokio::test]
    async fn a_wrong_method_is_405_json() {
        let (_, router) = app(None);
        for (method, path) in [
            (Method::DELETE, "/api/v1/jobs"),
            (Method::PUT, "/api/v1/jobs/1"),
            (Method::GET, "/api/v1/jobs/1/cancel"),
            (Method::POST, "/api/v1/workers"),
            (Method::POST, "/metrics"),
            (Method::POST, OPENAPI_PATH),
        ] {
            let request = axum::http::Request::builder()
                .method(method.clone())
                .uri(path)
                .body(Body::empty())
                .unwrap();
            let (status, headers, body) = call(&router, request).await;
            assert_eq!(status, StatusCode::METHOD_NOT_ALLOWED, "{method} {path}");
            assert!(headers.contains_key(header::ALLOW));
            let e = error_of(&headers, &body);
            assert!(e.contains(path) && e.contains("not allowed"), "{e}");
        }
    }

    #[tokio::test]
    async fn cancelling_an_ended_job_is_409() {
        let (_, router) = app(None);
        call(&router, post_json("/api/v1/jobs", spec_json("x"))).await;
        let (status, _, body) = call(&router, post_json("/api/v1/jobs/1/cancel", "")).await;
        assert_eq!(status, StatusCode::OK);
        assert_eq!(
            serde_json::from_slice::<JobView>(&body).unwrap().state,
            JobState::Cancelled
        );
        let (status, headers, body) = call(&router, post_json("/api/v1/jobs/1/cancel", "")).await;
        assert_eq!(status, StatusCode::CONFLICT);
        assert!(error_of(&headers, &body).contains("already ended"));
    }

    #[tokio::test]
    async fn oversized_bodies_and_scenes_are_413_json() {
        let (fake, router) = app(None);
        let body = spec_json(&"x".repeat(300 * 1024));
        let (status, headers, body) = call(&router, post_json("/api/v1/jobs", body)).await;
        assert_eq!(status, StatusCode::PAYLOAD_TOO_LARGE);
        error_of(&headers, &body);
        // Without a Content-Length the limit holds as well.
        let chunks = futures_chunks(300 * 1024);
        let (status, headers, body) = call(&router, post_json("/api/v1/jobs", chunks)).await;
        assert_eq!(status, StatusCode::PAYLOAD_TOO_LARGE);
        error_of(&headers, &body);

        let body = spec_json(&"x".repeat(70 * 1024));
        let (status, headers, body) = call(&router, post_json("/api/v1/jobs", body)).await;
        assert_eq!(status, StatusCode::PAYLOAD_TOO_LARGE);
        let e = error_of(&headers, &body);
        assert!(e.contains("65536") && e.contains("64 KiB"), "{e}");
        assert!(fake.jobs.lock().unwrap().is_empty());
    }

    /// A streamed body of `n` bytes (no Content-Length).
    fn futures_chunks(n: usize) -> Body {
        let chunks: Vec<Result<Bytes, std::io::Error>> = (0..n / 1024)
            .map(|_| Ok(Bytes::from(vec![b' '; 1024])))
            .collect();
        Body::from_stream(tokio_stream::iter(chunks))
    }

    #[tokio::test]
    async fn metrics_are_prometheus_text() {
        let (_, router) = app(None);
        let (status, headers, body) = call(&router, get("/metrics")).await;
        assert_eq!(status, StatusCode::OK);
        assert_eq!(headers[header::CONTENT_TYPE], METRICS_CONTENT_TYPE);
        assert!(String::from_utf8_lossy(&body).starts_with("hypertexture_jobs"));
    }

    #[tokio::test]
    async fn the_openapi_document_lists_exactly_the_routes() {
        let (_, router) = app(None);
        let (status, headers, body) = call(&router, get(OPENAPI_PATH)).await;
        assert_eq!(status, StatusCode::OK);
        assert!(is_json(&headers));
        let doc: serde_json::Value = serde_json::from_slice(&body).unwrap();
        assert!(doc["openapi"].as_str().unwrap().starts_with("3."));
        let paths: BTreeSet<(String, String)> = doc["paths"]
            .as_object()
            .unwrap()
            .iter()
            .flat_map(|(path, item)| {
                item.as_object()
                    .unwrap()
                    .keys()
                    .map(move |method| (path.clone(), method.clone()))
            })
            .collect();
        let want: BTreeSet<(String, String)> = [
            ("/api/v1/jobs", "get"),
            ("/api/v1/jobs", "post"),
            ("/api/v1/jobs/{id}", "get"),
            ("/api/v1/jobs/{id}/cancel", "post"),
            ("/api/v1/workers", "get"),
            ("/metrics", "get"),
            ("/readyz", "get"),
        ]
        .into_iter()
        .map(|(p, m)| (p.to_string(), m.to_string()))
        .collect();
        assert_eq!(paths, want);
        let schemas = doc["components"]["schemas"].as_object().unwrap();
        for name in [
            "JobSpec",
            "JobView",
            "WorkerView",
            "JobState",
            "QualitySpec",
            "ErrorBody",
        ] {
            assert!(schemas.contains_key(name), "{name}");
        }
        assert_eq!(
            doc["components"]["securitySchemes"]["bearer"]["scheme"],
            "bearer"
        );
        let submit = &doc["paths"]["/api/v1/jobs"]["post"]["responses"];
        for code in ["201", "400", "401", "413", "503", "507"] {
            assert!(submit.get(code).is_some(), "{code}");
        }
        assert!(doc["paths"]["/api/v1/jobs/{id}/cancel"]["post"]["responses"]["409"].is_object());
        assert!(doc["paths"]["/api/v1/jobs/{id}"]["get"]["responses"]["404"].is_object());
        // Every documented route answers (not 404/405) in the router.
        for (path, method) in &want {
            let path = path.replace("{id}", "1");
            let request = axum::http::Request::builder()
                .method(method.to_uppercase().as_str())
                .uri(&path)
                .header(header::CONTENT_TYPE, "application/json")
                .body(Body::from("{}"))
                .unwrap();
            let status = call(&router, request).await.0;
            assert!(
                status != StatusCode::METHOD_NOT_ALLOWED,
                "{method} {path}: {status}"
            );
            assert!(
                status != StatusCode::NOT_FOUND || path.contains('1'),
                "{method} {path}: {status}"
            );
        }
        assert_eq!(openapi().paths.paths.len(), 6);
    }

    #[tokio::test]
    async fn routes_added_later_are_not_shadowed_nor_wrapped() {
        let (_, router) = app(Some("s3cret"));
        let router = router.route_service(
            "/hypertexture.v1.Farm/{*rest}",
            tower::service_fn(|_req: Request| async {
                Ok::<_, std::convert::Infallible>(
                    ([(header::CONTENT_TYPE, "application/grpc")], "grpc").into_response(),
                )
            }),
        );
        let request = axum::http::Request::post("/hypertexture.v1.Farm/Work")
            .header(header::CONTENT_TYPE, "application/grpc")
            .body(Body::empty())
            .unwrap();
        let (status, headers, body) = call(&router, request).await;
        assert_eq!(status, StatusCode::OK);
        assert_eq!(headers[header::CONTENT_TYPE], "application/grpc");
        assert_eq!(&body[..], b"grpc");

        // An unknown gRPC method gets UNIMPLEMENTED (12), token or not.
        let request = axum::http::Request::post("/hypertexture.v1.Other/Call")
            .header(header::CONTENT_TYPE, "application/grpc+proto")
            .body(Body::empty())
            .unwrap();
        let (status, headers, _) = call(&router, request).await;
        assert_eq!(status, StatusCode::OK);
        assert_eq!(headers["grpc-status"], "12");
        // Any other unknown path is a JSON 404 (there is nothing to protect).
        let (status, headers, body) = call(&router, get("/nowhere")).await;
        assert_eq!(status, StatusCode::NOT_FOUND);
        assert!(error_of(&headers, &body).contains("/nowhere"));
    }

    /// A request from the proptest's parts.
    fn arbitrary_request(
        method: &str,
        suffix: &str,
        body: Vec<u8>,
        content_type: Option<Vec<u8>>,
        authorization: Option<Vec<u8>>,
    ) -> Option<axum::http::Request<Body>> {
        let mut request = axum::http::Request::builder()
            .method(method)
            .uri(format!("/api/v1/{suffix}"));
        if let Some(c) = content_type {
            request = request.header(header::CONTENT_TYPE, HeaderValue::from_bytes(&c).ok()?);
        }
        if let Some(a) = authorization {
            request = request.header(header::AUTHORIZATION, HeaderValue::from_bytes(&a).ok()?);
        }
        request.body(Body::from(body)).ok()
    }

    fn json_value() -> impl Strategy<Value = serde_json::Value> {
        let leaf = prop_oneof![
            Just(serde_json::Value::Null),
            any::<bool>().prop_map(serde_json::Value::from),
            any::<i64>().prop_map(serde_json::Value::from),
            any::<f64>().prop_map(serde_json::Value::from),
            ".{0,20}".prop_map(serde_json::Value::from),
            prop_oneof![
                Just("scene"),
                Just("out"),
                Just("frames"),
                Just("quality"),
                Just("knobs")
            ]
            .prop_map(serde_json::Value::from),
        ];
        leaf.prop_recursive(3, 24, 6, |inner| {
            prop_oneof![
                prop::collection::vec(inner.clone(), 0..6).prop_map(serde_json::Value::Array),
                prop::collection::btree_map(
                    prop_oneof![
                        Just("scene".to_string()),
                        Just("out".to_string()),
                        Just("frames".to_string()),
                        Just("priority".to_string()),
                        Just("quality".to_string()),
                        Just("knobs".to_string()),
                        "[a-z_]{1,8}",
                    ],
                    inner,
                    0..6
                )
                .prop_map(|m| serde_json::Value::Object(m.into_iter().collect())),
            ]
        })
    }

    fn body() -> impl Strategy<Value = Vec<u8>> {
        prop_oneof![
            json_value().prop_map(|v| v.to_string().into_bytes()),
            prop::collection::vec(any::<u8>(), 0..200),
        ]
    }

    fn suffix() -> impl Strategy<Value = String> {
        prop_oneof![
            Just("jobs".to_string()),
            Just("workers".to_string()),
            Just("openapi.json".to_string()),
            "jobs/[0-9]{1,25}",
            "jobs/[0-9]{1,3}/cancel",
            "jobs/[a-z%0-9.]{0,12}(/cancel)?",
            "[a-zA-Z0-9/%._~-]{0,30}",
        ]
    }

    proptest! {
        #![proptest_config(ProptestConfig { cases: 128, ..ProptestConfig::default() })]

        #[test]
        fn arbitrary_requests_are_refused_as_json_and_never_fail(
            method in prop_oneof![Just("GET"), Just("POST"), Just("PUT"), Just("DELETE"), Just("PATCH"), Just("HEAD")],
            suffix in suffix(),
            body in body(),
            content_type in prop::option::of(prop_oneof![
                Just(b"application/json".to_vec()),
                Just(b"application/json; charset=utf-8".to_vec()),
                prop::collection::vec(any::<u8>(), 0..30),
            ]),
            authorization in prop::option::of(prop_oneof![
                Just(b"Bearer s3cret".to_vec()),
                prop::collection::vec(any::<u8>(), 0..30),
            ]),
            with_token in any::<bool>(),
        ) {
            let Some(request) = arbitrary_request(method, &suffix, body, content_type, authorization) else {
                return Ok(());
            };
            let runtime = tokio::runtime::Builder::new_current_thread().enable_time().build().unwrap();
            let (_, router) = app(with_token.then_some("s3cret"));
            let (status, headers, body) = runtime.block_on(async {
                tokio::time::timeout(Duration::from_secs(10), call(&router, request)).await
            }).expect("the request completes");
            prop_assert!(status.is_success() || status.is_client_error(), "{status}");
            if !status.is_success() && method != "HEAD" {
                prop_assert!(is_json(&headers));
                let e: ErrorBody = serde_json::from_slice(&body).unwrap();
                prop_assert!(!e.error.is_empty() && !e.error.contains('\n'));
            }
        }
    }
}
