//! The clients of `coordinator serve`: submit, status, cancel, wait.
//!
//! Each call is a blocking HTTP/1.1 request (ureq) to the service's JSON API
//! (see [`crate::service::api`]) at `--server` (`http://` or `https://`), with
//! `Authorization: Bearer <--token>` when a token is given, and, for
//! `https://` with `--ca FILE`, that PEM certificate as the only trusted root
//! (a self-signed CA works). Connecting and each read give up after
//! [`TIMEOUT`], so a dead or stuck server never hangs a client.

use std::fmt::Write as _;
use std::path::{Path, PathBuf};
use std::thread;
use std::time::{Duration, Instant};

use serde::Serialize;
use serde::de::DeserializeOwned;

use crate::service::jobs::{JobSpec, JobView, WorkerView};

/// How long connecting, sending and each wait for an answer may take.
pub const TIMEOUT: Duration = Duration::from_secs(10);

/// How often `wait` asks for the job's state.
pub const POLL_EVERY: Duration = Duration::from_millis(200);

/// How long `wait` keeps retrying while the server cannot be reached
/// (a restart of the service does not end the wait).
pub const RECONNECT_FOR: Duration = Duration::from_secs(30);

/// The largest answer read (bytes).
const MAX_ANSWER_BYTES: u64 = 64 * 1024 * 1024;

/// The width the status table keeps within.
const COLUMNS: usize = 80;

/// The narrowest error column of the jobs table; when less room is left the
/// errors go on lines of their own below it.
const MIN_ERROR_COLUMN: usize = 16;

/// Why a client call failed.
#[derive(Debug, thiserror::Error)]
pub enum ClientError {
    /// `--server` is not an `http://` or `https://` URL.
    #[error("--server {url}: {message}")]
    BadServer {
        /// The URL given.
        url: String,
        /// What is wrong with it.
        message: String,
    },
    /// The server could not be reached (refused, unknown host, TLS failure, time-out).
    #[error(
        "cannot reach the coordinator at {url}: {message} (is `coordinator serve` running there?)"
    )]
    Unreachable {
        /// The URL requested.
        url: String,
        /// What failed.
        message: String,
    },
    /// The server answered with an error status.
    #[error("the coordinator refused {method} {url}: HTTP {status}: {message}")]
    Refused {
        /// The request's method.
        method: &'static str,
        /// The URL requested.
        url: String,
        /// The HTTP status.
        status: u16,
        /// The server's `error` message (or its status text).
        message: String,
    },
    /// The scene file could not be used (unreadable, over 64 KiB, not UTF-8).
    #[error(transparent)]
    Scene(#[from] hypertexture::SceneError),
    /// Another local file or path could not be used (the CA certificate, the output path).
    #[error("{path}: {message}")]
    LocalFile {
        /// The file.
        path: PathBuf,
        /// What is wrong.
        message: String,
    },
    /// The server's answer could not be understood.
    #[error("the coordinator's answer to {method} {url} is not {expected}: {message}")]
    BadAnswer {
        /// The request's method.
        method: &'static str,
        /// The URL requested.
        url: String,
        /// What was expected.
        expected: &'static str,
        /// What was wrong.
        message: String,
    },
}

/// Where the service is and how to reach it (`--server`, `--token`, `--ca`).
#[derive(Clone, Debug)]
pub struct Endpoint {
    /// The service's URL (`http://` or `https://`).
    pub url: String,
    /// The service's token (empty: none).
    pub token: Option<String>,
    /// A CA certificate (PEM) to verify an `https://` service.
    pub ca: Option<PathBuf>,
}

/// A connection to the service: the agent, the base URL and the token.
struct Client {
    agent: ureq::Agent,
    base: String,
    token: Option<String>,
}

impl Client {
    /// A client for `args`: checks the URL, reads the CA certificate.
    fn new(args: &Endpoint) -> Result<Client, ClientError> {
        let url = args.url.trim();
        let bad = |message: &str| ClientError::BadServer {
            url: args.url.clone(),
            message: message.into(),
        };
        let rest = url
            .strip_prefix("http://")
            .or_else(|| url.strip_prefix("https://"))
            .ok_or_else(|| bad("expected http://HOST:PORT or https://HOST:PORT"))?;
        if rest.trim_end_matches('/').is_empty() {
            return Err(bad("the URL names no host"));
        }
        let mut config = ureq::Agent::config_builder()
            .http_status_as_error(false)
            .max_redirects(0)
            .timeout_connect(Some(TIMEOUT))
            .timeout_send_request(Some(TIMEOUT))
            .timeout_send_body(Some(TIMEOUT))
            .timeout_recv_response(Some(TIMEOUT))
            .timeout_recv_body(Some(TIMEOUT))
            .user_agent(concat!("coordinator/", env!("CARGO_PKG_VERSION")));
        if let Some(ca) = &args.ca {
            config = config.tls_config(
                ureq::tls::TlsConfig::builder()
                    .root_certs(ureq::tls::RootCerts::new_with_certs(&read_ca(ca)?))
                    .build(),
            );
        }
        Ok(Client {
            agent: config.build().into(),
            base: url.trim_end_matches('/').to_string(),
            token: args.token.clone().filter(|t| !t.is_empty()),
        })
    }

    /// The URL of `path` (which starts with `/`).
    fn url(&self, path: &str) -> String {
        format!("{}{path}", self.base)
    }

    /// GET `path`, expecting 200 and a `T`.
    fn get<T: DeserializeOwned>(
        &self,
        path: &str,
        expected: &'static str,
    ) -> Result<T, ClientError> {
        let url = self.url(path);
        let mut request = self.agent.get(&url);
        if let Some(t) = &self.token {
            request = request.header("Authorization", format!("Bearer {t}"));
        }
        answer("GET", &url, request.call(), 200, expected)
    }

    /// GET `path`, expecting 200 and a `T`, and the path of the next page
    /// its `Link: <…>; rel="next"` header names.
    fn get_page<T: DeserializeOwned>(
        &self,
        path: &str,
        expected: &'static str,
    ) -> Result<(T, Option<String>), ClientError> {
        let url = self.url(path);
        let mut request = self.agent.get(&url);
        if let Some(t) = &self.token {
            request = request.header("Authorization", format!("Bearer {t}"));
        }
        let result = request.call();
        let next = result.as_ref().ok().and_then(|r| {
            let link = r.headers().get("link")?.to_str().ok()?;
            next_link(link)
        });
        Ok((answer("GET", &url, result, 200, expected)?, next))
    }

    /// POST `body` (JSON; none: empty) to `path`, expecting `status` and a `T`.
    fn post<T: DeserializeOwned>(
        &self,
        path: &str,
        body: Option<&impl Serialize>,
        status: u16,
        expected: &'static str,
    ) -> Result<T, ClientError> {
        let url = self.url(path);
        let mut request = self.agent.post(&url);
        if let Some(t) = &self.token {
            request = request.header("Authorization", format!("Bearer {t}"));
        }
        let result = match body {
            Some(b) => request.send_json(b),
            None => request.send_empty(),
        };
        answer("POST", &url, result, status, expected)
    }
}

/// The target of the `rel="next"` entry of a `Link` header (RFC 8288), when
/// it is a path of the service.
fn next_link(link: &str) -> Option<String> {
    link.split(',').find_map(|entry| {
        let (target, params) = entry.trim().split_once(';')?;
        let target = target.trim().strip_prefix('<')?.strip_suffix('>')?;
        let next = params
            .split(';')
            .any(|p| p.trim().eq_ignore_ascii_case("rel=\"next\""));
        (next && target.starts_with('/')).then(|| target.to_string())
    })
}

/// Pages of `GET /api/v1/jobs` `coordinator status` reads at most (of
/// [`MAX_PAGE`](crate::service::limits::MAX_PAGE) jobs each).
const MAX_STATUS_PAGES: usize = 1000;

/// The certificates of the PEM file `path`.
fn read_ca(path: &Path) -> Result<Vec<ureq::tls::Certificate<'static>>, ClientError> {
    let local = |message: String| ClientError::LocalFile {
        path: path.to_path_buf(),
        message,
    };
    let pem = crate::files::read_capped(path, crate::files::MAX_PEM_BYTES, "CA certificate")
        .map_err(|e| local(e.to_string()))?;
    let mut certs = Vec::new();
    for item in ureq::tls::parse_pem(&pem) {
        match item {
            Ok(ureq::tls::PemItem::Certificate(c)) => certs.push(c),
            Ok(_) => {}
            Err(e) => return Err(local(format!("not a PEM CA certificate: {e}"))),
        }
    }
    if certs.is_empty() {
        return Err(local(
            "holds no PEM certificate (-----BEGIN CERTIFICATE-----)".into(),
        ));
    }
    Ok(certs)
}

/// The `T` of an answer with `want` status; a refusal or failure as [`ClientError`].
fn answer<T: DeserializeOwned>(
    method: &'static str,
    url: &str,
    result: Result<ureq::http::Response<ureq::Body>, ureq::Error>,
    want: u16,
    expected: &'static str,
) -> Result<T, ClientError> {
    let mut response = result.map_err(|e| transport_error(url, e))?;
    let status = response.status().as_u16();
    let text = response
        .body_mut()
        .with_config()
        .limit(MAX_ANSWER_BYTES)
        .read_to_string()
        .map_err(|e| transport_error(url, e))?;
    if status != want {
        let mut message = serde_json::from_str::<crate::service::api::ErrorBody>(&text)
            .map(|b| b.error)
            .ok()
            .or_else(|| {
                text.lines()
                    .map(str::trim)
                    .find(|l| !l.is_empty())
                    .map(|l| l.chars().take(200).collect())
            })
            .unwrap_or_else(|| {
                response
                    .status()
                    .canonical_reason()
                    .unwrap_or("no message")
                    .to_lowercase()
            });
        if status == 401 {
            message.push_str(" (give the service's token with --token or HYPERTEXTURE_TOKEN)");
        }
        return Err(ClientError::Refused {
            method,
            url: url.to_string(),
            status,
            message,
        });
    }
    serde_json::from_str(&text).map_err(|e| ClientError::BadAnswer {
        method,
        url: url.to_string(),
        expected,
        message: e.to_string(),
    })
}

/// A failure below HTTP as [`ClientError`].
fn transport_error(url: &str, e: ureq::Error) -> ClientError {
    match e {
        ureq::Error::BadUri(message) => ClientError::BadServer {
            url: url.to_string(),
            message,
        },
        ureq::Error::Http(e) => ClientError::BadServer {
            url: url.to_string(),
            message: e.to_string(),
        },
        e => ClientError::Unreachable {
            url: url.to_string(),
            message: e.to_string(),
        },
    }
}

/// `job` with the scene's text and name read from the file `scene`, and a
/// relative output made absolute against this process's current directory
/// (the service writes the images on its own machine, from its own
/// directory).
pub fn read_job(scene: &Path, job: JobSpec) -> Result<JobSpec, ClientError> {
    let scene_text = hypertexture::scene::read_text(scene)?;
    let out = Path::new(&job.out);
    let out = if out.is_absolute() {
        job.out.clone()
    } else {
        std::path::absolute(out)
            .map_err(|e| ClientError::LocalFile {
                path: out.to_path_buf(),
                message: format!("cannot make the output path absolute: {e}"),
            })?
            .display()
            .to_string()
    };
    Ok(JobSpec {
        request: hypertexture::RenderRequest {
            scene_text,
            scene_name: scene.display().to_string(),
            ..job.request
        },
        out,
        ..job
    })
}

/// `coordinator submit`: queues the job, returns its id.
pub fn submit(server: &Endpoint, spec: &JobSpec) -> Result<u64, ClientError> {
    let client = Client::new(server)?;
    let job: JobView = client.post("/api/v1/jobs", Some(spec), 201, "a job")?;
    Ok(job.id)
}

/// `coordinator status`: the table to print (every job and worker), or with
/// a job id, that job's details.
pub fn status(server: &Endpoint, job: Option<u64>) -> Result<String, ClientError> {
    let client = Client::new(server)?;
    match job {
        Some(id) => {
            let job: JobView = client.get(&format!("/api/v1/jobs/{id}"), "a job")?;
            Ok(job_details(&job))
        }
        None => {
            let mut jobs: Vec<JobView> = Vec::new();
            let mut path = format!("/api/v1/jobs?limit={}", crate::service::limits::MAX_PAGE);
            for _ in 0..MAX_STATUS_PAGES {
                let (page, next): (Vec<JobView>, _) = client.get_page(&path, "a list of jobs")?;
                jobs.extend(page);
                match next {
                    Some(next) if next != path => path = next,
                    _ => break,
                }
            }
            let workers: Vec<WorkerView> = client.get("/api/v1/workers", "a list of workers")?;
            let ready: Result<crate::service::api::Ready, _> = client.get("/readyz", "readiness");
            let table = status_table(&jobs, &workers);
            Ok(match ready {
                // Not ready: why, above the table (the store cannot write).
                Err(ClientError::Refused {
                    status: 503,
                    message,
                    ..
                }) => format!("NOT READY: {message}\n{table}"),
                _ => table,
            })
        }
    }
}

/// `coordinator cancel`: the job as cancelled.
pub fn cancel(server: &Endpoint, job: u64) -> Result<JobView, ClientError> {
    let client = Client::new(server)?;
    client.post(
        &format!("/api/v1/jobs/{job}/cancel"),
        None::<&()>,
        200,
        "a job",
    )
}

/// `coordinator wait`: the job once it has ended (done, failed or cancelled).
/// Asks every [`POLL_EVERY`]; while the server cannot be reached it keeps
/// trying for [`RECONNECT_FOR`] before giving up.
pub fn wait(server: &Endpoint, job: u64) -> Result<JobView, ClientError> {
    wait_with(server, job, POLL_EVERY, RECONNECT_FOR)
}

/// [`wait`] with its poll interval and reconnection patience.
fn wait_with(
    server: &Endpoint,
    job: u64,
    every: Duration,
    patience: Duration,
) -> Result<JobView, ClientError> {
    let client = Client::new(server)?;
    let path = format!("/api/v1/jobs/{job}");
    let mut unreachable_since: Option<Instant> = None;
    loop {
        match client.get::<JobView>(&path, "a job") {
            Ok(job) if job.state.is_final() => return Ok(job),
            Ok(_) => unreachable_since = None,
            Err(e @ ClientError::Unreachable { .. }) => {
                let since = *unreachable_since.get_or_insert_with(Instant::now);
                if since.elapsed() >= patience {
                    return Err(e);
                }
            }
            Err(e) => return Err(e),
        }
        thread::sleep(every);
    }
}

/// `12s`, `3m04s`, `2h05m`; `-` when unknown.
pub fn format_eta(seconds: Option<f64>) -> String {
    let Some(s) = seconds.filter(|s| s.is_finite() && *s >= 0.0) else {
        return "-".into();
    };
    let s = s.round() as u64;
    match s {
        0..60 => format!("{s}s"),
        60..3600 => format!("{}m{:02}s", s / 60, s % 60),
        _ => format!("{}h{:02}m", s / 3600, (s % 3600) / 60),
    }
}

/// `950`, `12.3k`, `4.5M`.
fn format_rate(r: f64) -> String {
    if !r.is_finite() || r < 0.0 {
        "-".into()
    } else if r < 1e3 {
        format!("{r:.0}")
    } else if r < 1e6 {
        format!("{:.1}k", r / 1e3)
    } else {
        format!("{:.1}M", r / 1e6)
    }
}

/// `s` cut to `max` characters, ending in `…` when cut.
fn truncate(s: &str, max: usize) -> String {
    if s.chars().count() <= max {
        return s.to_string();
    }
    let mut out: String = s.chars().take(max.saturating_sub(1)).collect();
    out.push('…');
    out
}

/// `s` cut to its last `max` characters, starting with `…` when cut (a
/// path keeps its file name).
fn truncate_start(s: &str, max: usize) -> String {
    let n = s.chars().count();
    if n <= max {
        return s.to_string();
    }
    let keep = max.saturating_sub(1);
    std::iter::once('…')
        .chain(s.chars().skip(n - keep))
        .collect()
}

/// `items` comma-separated, or `-`.
fn list_or_dash<T: ToString>(items: &[T]) -> String {
    if items.is_empty() {
        "-".into()
    } else {
        items
            .iter()
            .map(ToString::to_string)
            .collect::<Vec<_>>()
            .join(",")
    }
}

/// The width of each column of `rows` under `header`.
fn column_widths(header: &[&str], rows: &[Vec<String>]) -> Vec<usize> {
    let mut widths: Vec<usize> = header.iter().map(|h| h.chars().count()).collect();
    for row in rows {
        for (w, cell) in widths.iter_mut().zip(row) {
            *w = (*w).max(cell.chars().count());
        }
    }
    widths
}

/// `rows` under `header` with aligned columns (two spaces apart); the last
/// column is cut to keep lines within [`COLUMNS`].
fn table(header: &[&str], rows: &[Vec<String>]) -> String {
    let n = header.len();
    let widths = column_widths(header, rows);
    let before_last: usize = widths[..n - 1].iter().map(|w| w + 2).sum();
    let last_max = COLUMNS.saturating_sub(before_last).max(8);
    let mut out = String::new();
    let header: Vec<String> = header.iter().map(|h| h.to_string()).collect();
    for row in std::iter::once(&header).chain(rows) {
        let mut line = String::new();
        for (i, cell) in row.iter().enumerate() {
            if i + 1 == n {
                line.push_str(&truncate(cell, last_max));
            } else {
                let _ = write!(line, "{cell:<w$}  ", w = widths[i]);
            }
        }
        out.push_str(line.trim_end());
        out.push('\n');
    }
    out
}

/// The two sections of `coordinator status`: jobs and workers.
pub fn status_table(jobs: &[JobView], workers: &[WorkerView]) -> String {
    let mut out = String::new();
    let _ = writeln!(out, "jobs: {}", jobs.len());
    if !jobs.is_empty() {
        let header = ["ID", "STATE", "PRI", "FRAMES", "UNITS", "ETA", "SCENE"];
        let mut rows: Vec<Vec<String>> = jobs
            .iter()
            .map(|j| {
                vec![
                    j.id.to_string(),
                    j.state.as_str().to_string(),
                    j.priority.to_string(),
                    format!("{}/{}", j.frames_done, j.frames_total),
                    format!("{}/{}", j.units_done, j.units_total),
                    format_eta(j.eta_seconds),
                    truncate_start(&j.scene_name, 24),
                ]
            })
            .collect();
        let error = |j: &JobView| j.error.as_deref().map(|e| e.replace(['\n', '\r'], " "));
        let used: usize = column_widths(&header, &rows).iter().map(|w| w + 2).sum();
        if COLUMNS.saturating_sub(used) >= MIN_ERROR_COLUMN {
            for (row, j) in rows.iter_mut().zip(jobs) {
                row.push(error(j).unwrap_or_else(|| "-".into()));
            }
            let mut header = header.to_vec();
            header.push("ERROR");
            out.push_str(&table(&header, &rows));
        } else {
            // Too narrow for an error column: each error on a line of its own.
            out.push_str(&table(&header, &rows));
            for j in jobs {
                if let Some(e) = error(j) {
                    let line = format!("job {}: {e}", j.id);
                    let _ = writeln!(out, "{}", truncate(&line, COLUMNS));
                }
            }
        }
    }
    out.push('\n');
    let _ = writeln!(out, "workers: {}", workers.len());
    if !workers.is_empty() {
        let rows: Vec<Vec<String>> = workers
            .iter()
            .map(|w| {
                vec![
                    truncate(&w.name, 20),
                    truncate(&list_or_dash(&w.tags), 20),
                    format_rate(w.pixels_per_second),
                    w.current_job
                        .map_or_else(|| "idle".into(), |j| j.to_string()),
                    list_or_dash(&w.blocklisted_for),
                ]
            })
            .collect();
        out.push_str(&table(
            &["NAME", "TAGS", "PIXELS/S", "JOB", "BLOCKLISTED FOR"],
            &rows,
        ));
    }
    out
}

/// Every field of `job`, one a line, its outputs listed below.
pub fn job_details(job: &JobView) -> String {
    let mut out = String::new();
    let mut line = |name: &str, value: String| {
        let _ = writeln!(out, "{:<14}{value}", format!("{name}:"));
    };
    line("id", job.id.to_string());
    line("state", job.state.as_str().into());
    line("priority", job.priority.to_string());
    line("scene", job.scene_name.clone());
    line("out", job.out.clone());
    line(
        "frames",
        format!("{}/{} done", job.frames_done, job.frames_total),
    );
    line(
        "units",
        format!("{}/{} done", job.units_done, job.units_total),
    );
    line("eta", format_eta(job.eta_seconds));
    line(
        "error",
        job.error
            .as_deref()
            .map_or_else(|| "-".into(), |e| e.replace('\n', " ")),
    );
    line("require tags", list_or_dash(&job.require_tags));
    line("blocklisted", list_or_dash(&job.blocklisted));
    line("outputs", job.outputs.len().to_string());
    for o in &job.outputs {
        let _ = writeln!(out, "  {o}");
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_next_page_is_the_link_headers_rel_next() {
        assert_eq!(
            next_link("</api/v1/jobs?limit=2&cursor=7>; rel=\"next\"").as_deref(),
            Some("/api/v1/jobs?limit=2&cursor=7")
        );
        assert_eq!(
            next_link("<http://elsewhere/x>; rel=\"next\", </a>; rel=\"prev\""),
            None
        );
        assert_eq!(next_link("garbage"), None);
    }
    use crate::service::jobs::{ApiError, Control, JobState};
    use std::collections::BTreeMap;
    use std::sync::atomic::{AtomicU32, Ordering};
    use std::sync::{Arc, Mutex};

    /// A fake farm: a submitted job runs for `polls_to_finish` looks, then is done.
    #[derive(Default)]
    struct Farm {
        jobs: Mutex<Vec<JobView>>,
        specs: Mutex<Vec<JobSpec>>,
        looks: AtomicU32,
        polls_to_finish: u32,
    }

    impl Control for Farm {
        fn submit(&self, spec: JobSpec) -> Result<JobView, ApiError> {
            if spec.request.scene_text.contains("bad") {
                return Err(ApiError::BadRequest(format!(
                    "{}:3:7: expected `)` found `(`",
                    spec.request.scene_name
                )));
            }
            let mut jobs = self.jobs.lock().unwrap();
            let job = JobView {
                id: jobs.len() as u64 + 1,
                state: JobState::Queued,
                priority: spec.priority,
                scene_name: spec.request.scene_name.clone(),
                out: spec.out.clone(),
                frames_done: 0,
                frames_total: spec.request.frames.len() as u32,
                units_done: 0,
                units_total: 64,
                eta_seconds: None,
                error: None,
                outputs: Vec::new(),
                require_tags: spec.require_tags.clone(),
                blocklisted: Vec::new(),
            };
            jobs.push(job.clone());
            self.specs.lock().unwrap().push(spec);
            Ok(job)
        }
        fn jobs(&self) -> Vec<JobView> {
            self.jobs.lock().unwrap().iter().rev().cloned().collect()
        }
        fn job(&self, id: u64) -> Result<JobView, ApiError> {
            let mut jobs = self.jobs.lock().unwrap();
            let job = jobs
                .iter_mut()
                .find(|j| j.id == id)
                .ok_or(ApiError::NotFound(id))?;
            let looks = self.looks.fetch_add(1, Ordering::SeqCst) + 1;
            if !job.state.is_final() {
                job.state = JobState::Running;
                job.units_done = u64::from(looks).min(job.units_total);
                if looks >= self.polls_to_finish {
                    job.state = JobState::Done;
                    job.frames_done = job.frames_total;
                    job.outputs.push(job.out.clone());
                }
            }
            Ok(job.clone())
        }
        fn cancel(&self, id: u64) -> Result<JobView, ApiError> {
            let mut jobs = self.jobs.lock().unwrap();
            let job = jobs
                .iter_mut()
                .find(|j| j.id == id)
                .ok_or(ApiError::NotFound(id))?;
            if job.state.is_final() {
                return Err(ApiError::Conflict(format!("job {id} has already ended")));
            }
            job.state = JobState::Cancelled;
            Ok(job.clone())
        }
        fn workers(&self) -> Vec<WorkerView> {
            vec![
                WorkerView {
                    id: "w1".into(),
                    name: "render-box-1".into(),
                    tags: vec!["gpu".into(), "linux".into()],
                    threads: 8,
                    pixels_per_second: 123_456.0,
                    current_job: Some(1),
                    units: 12,
                    blocklisted_for: vec![],
                },
                WorkerView {
                    id: "w2".into(),
                    name: "laptop".into(),
                    tags: vec![],
                    threads: 2,
                    pixels_per_second: 950.0,
                    current_job: None,
                    units: 0,
                    blocklisted_for: vec![3, 4],
                },
            ]
        }
        fn metrics(&self) -> String {
            String::new()
        }
    }

    /// The API on `farm`, served on a loopback port until dropped.
    struct Server {
        url: String,
        stop: Option<tokio::sync::oneshot::Sender<()>>,
        thread: Option<thread::JoinHandle<()>>,
    }

    impl Server {
        fn start(farm: Arc<Farm>, token: Option<&str>) -> Server {
            let listener = std::net::TcpListener::bind("127.0.0.1:0").unwrap();
            listener.set_nonblocking(true).unwrap();
            let url = format!("http://{}", listener.local_addr().unwrap());
            let router = crate::service::api::router(farm, token.map(str::to_string));
            let (stop, stopped) = tokio::sync::oneshot::channel::<()>();
            let thread = thread::spawn(move || {
                let runtime = tokio::runtime::Builder::new_current_thread()
                    .enable_all()
                    .build()
                    .unwrap();
                runtime.block_on(async move {
                    let listener = tokio::net::TcpListener::from_std(listener).unwrap();
                    axum::serve(listener, router)
                        .with_graceful_shutdown(async move {
                            let _ = stopped.await;
                        })
                        .await
                        .unwrap();
                });
            });
            Server {
                url,
                stop: Some(stop),
                thread: Some(thread),
            }
        }
    }

    impl Drop for Server {
        fn drop(&mut self) {
            if let Some(s) = self.stop.take() {
                let _ = s.send(());
            }
            if let Some(t) = self.thread.take() {
                let _ = t.join();
            }
        }
    }

    fn server_args(url: &str, token: Option<&str>) -> Endpoint {
        Endpoint {
            url: url.to_string(),
            token: token.map(str::to_string),
            ca: None,
        }
    }

    /// A URL on loopback where nothing listens.
    fn dead_url() -> String {
        let listener = std::net::TcpListener::bind("127.0.0.1:0").unwrap();
        let url = format!("http://{}", listener.local_addr().unwrap());
        drop(listener);
        url
    }

    fn scene_file(dir: &str, text: &str) -> PathBuf {
        let dir =
            std::env::temp_dir().join(format!("coordinator-client-{dir}-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let path = dir.join("scene.ron");
        std::fs::write(&path, text).unwrap();
        path
    }

    /// The job `coordinator submit` sends for the scene file `scene`.
    fn job(scene: &Path) -> Result<JobSpec, ClientError> {
        let request = hypertexture::RenderRequest {
            overrides: hypertexture::Overrides {
                width: Some(320),
                height: None,
                spp: Some(4),
                quality: Some(hypertexture::Quality::Interactive),
                knobs: vec![("curliness".into(), 0.8), ("amp".into(), 2.0)],
            },
            frames: hypertexture::FrameRange { first: 2, last: 5 },
            ..hypertexture::RenderRequest::new("", "")
        };
        read_job(
            scene,
            JobSpec {
                request,
                out: "renders/fur.####.exr".into(),
                priority: -3,
                require_tags: vec!["gpu".into()],
            },
        )
    }

    fn submit_job(url: &str, token: Option<&str>, scene: PathBuf) -> Result<u64, ClientError> {
        submit(&server_args(url, token), &job(&scene)?)
    }

    #[test]
    fn submit_status_cancel_and_wait_against_the_api() {
        let farm = Arc::new(Farm {
            polls_to_finish: 3,
            ..Farm::default()
        });
        let server = Server::start(farm.clone(), Some("tok"));
        let scene = scene_file("submit", "Scene(name: \"fur\")");
        let id = submit_job(&server.url, Some("tok"), scene.clone()).unwrap();
        assert_eq!(id, 1);
        let spec = crate::service::jobs::JobJson::from(farm.specs.lock().unwrap()[0].clone());
        assert_eq!(spec.scene, "Scene(name: \"fur\")");
        assert_eq!(
            spec.scene_name.as_deref(),
            Some(scene.display().to_string().as_str())
        );
        let out = std::env::current_dir()
            .unwrap()
            .join("renders/fur.####.exr");
        assert_eq!(spec.out, out.display().to_string());
        assert_eq!(spec.frames, Some([2, 5]));
        assert_eq!(spec.priority, -3);
        assert_eq!(
            (spec.width, spec.height, spec.spp),
            (Some(320), None, Some(4))
        );
        assert_eq!(spec.quality, Some(hypertexture::Quality::Interactive));
        assert_eq!(
            spec.knobs,
            BTreeMap::from([("amp".to_string(), 2.0), ("curliness".to_string(), 0.8)])
        );
        assert_eq!(spec.require_tags, vec!["gpu".to_string()]);

        let table = status(&server_args(&server.url, Some("tok")), None).unwrap();
        assert!(
            table.contains("jobs: 1") && table.contains("workers: 2"),
            "{table}"
        );
        assert!(
            table.contains("render-box-1") && table.contains("gpu,linux"),
            "{table}"
        );
        assert!(
            table.contains("123.5k") && table.contains("idle") && table.contains("3,4"),
            "{table}"
        );
        assert!(
            table.contains("queued") && table.contains("0/4") && table.contains("0/64"),
            "{table}"
        );
        assert!(
            table.lines().all(|l| l.chars().count() <= COLUMNS),
            "{table}"
        );

        let job = (server_args(&server.url, Some("tok")), 1);
        let done = wait_with(
            &job.0,
            job.1,
            Duration::from_millis(10),
            Duration::from_secs(5),
        )
        .unwrap();
        assert_eq!(done.state, JobState::Done);
        assert!(farm.looks.load(Ordering::SeqCst) >= 3);

        let details = status(&server_args(&server.url, Some("tok")), Some(1)).unwrap();
        assert!(details.contains("state:        done"), "{details}");
        assert!(
            details.contains(&format!("  {}", out.display())),
            "{details}"
        );

        let e = cancel(&job.0, job.1).unwrap_err().to_string();
        assert!(
            e.contains("HTTP 409") && e.contains("job 1 has already ended"),
            "{e}"
        );
        submit_job(&server.url, Some("tok"), scene).unwrap();
        let cancelled = cancel(&server_args(&server.url, Some("tok")), 2).unwrap();
        assert_eq!((cancelled.id, cancelled.state), (2, JobState::Cancelled));
        let e = cancel(&server_args(&server.url, Some("tok")), 9).unwrap_err();
        assert!(matches!(e, ClientError::Refused { status: 404, .. }), "{e}");
        assert!(e.to_string().contains("no job 9"), "{e}");
    }

    #[test]
    fn refusals_carry_the_servers_message() {
        let server = Server::start(Arc::new(Farm::default()), Some("tok"));
        let scene = scene_file("refusal", "bad scene");
        let e = submit_job(&server.url, Some("tok"), scene.clone()).unwrap_err();
        let message = e.to_string();
        assert!(
            matches!(e, ClientError::Refused { status: 400, .. }),
            "{message}"
        );
        assert!(
            message.contains(&format!("{}:3:7: expected `)` found `(`", scene.display())),
            "{message}"
        );
        assert!(message.contains("/api/v1/jobs"), "{message}");
        let e = status(&server_args(&server.url, Some("wrong")), None).unwrap_err();
        assert!(matches!(e, ClientError::Refused { status: 401, .. }), "{e}");
        assert!(e.to_string().contains("--token"), "{e}");
    }

    #[test]
    fn a_dead_server_is_named_with_a_hint() {
        let url = dead_url();
        let scene = scene_file("dead", "Scene()");
        let e = submit_job(&url, None, scene).unwrap_err();
        let message = e.to_string();
        assert!(matches!(e, ClientError::Unreachable { .. }), "{message}");
        assert!(
            message.contains(&url) && message.contains("coordinator serve"),
            "{message}"
        );
        assert!(!message.contains('\n'));

        let start = Instant::now();
        let job = (server_args(&url, None), 1);
        let e = wait_with(
            &job.0,
            job.1,
            Duration::from_millis(20),
            Duration::from_millis(300),
        )
        .unwrap_err();
        assert!(matches!(e, ClientError::Unreachable { .. }), "{e}");
        let took = start.elapsed();
        assert!(
            took >= Duration::from_millis(300) && took < Duration::from_secs(10),
            "{took:?}"
        );
    }

    #[test]
    fn wait_outlasts_a_restart() {
        let listener = std::net::TcpListener::bind("127.0.0.1:0").unwrap();
        let addr = listener.local_addr().unwrap();
        drop(listener);
        let farm = Arc::new(Farm {
            polls_to_finish: 2,
            ..Farm::default()
        });
        farm.submit(JobSpec {
            request: hypertexture::RenderRequest::new("", "scene.ron"),
            out: "/tmp/x.png".into(),
            priority: 0,
            require_tags: Vec::new(),
        })
        .unwrap();
        // The server comes up 300 ms after the wait begins.
        let starter = {
            let farm = farm.clone();
            thread::spawn(move || {
                thread::sleep(Duration::from_millis(300));
                let router = crate::service::api::router(farm, None);
                let runtime = tokio::runtime::Builder::new_current_thread()
                    .enable_all()
                    .build()
                    .unwrap();
                runtime.block_on(async move {
                    let listener = tokio::net::TcpListener::bind(addr).await.unwrap();
                    let _ = tokio::time::timeout(
                        Duration::from_secs(10),
                        axum::serve(listener, router).into_future(),
                    )
                    .await;
                });
            })
        };
        let job = (server_args(&format!("http://{addr}"), None), 1);
        let done = wait_with(
            &job.0,
            job.1,
            Duration::from_millis(20),
            Duration::from_secs(5),
        )
        .unwrap();
        assert_eq!(done.state, JobState::Done);
        drop(starter);
    }

    #[test]
    fn local_failures_name_the_file() {
        let url = dead_url();
        let missing = std::env::temp_dir().join("coordinator-client-no-such-scene.ron");
        let e = submit_job(&url, None, missing.clone()).unwrap_err();
        assert!(matches!(e, ClientError::Scene(_)), "{e}");
        assert!(
            e.to_string().contains(&missing.display().to_string()),
            "{e}"
        );

        let big = scene_file("big", &"x".repeat(hypertexture::scene::MAX_SCENE_BYTES + 1));
        let e = submit_job(&url, None, big).unwrap_err();
        assert!(matches!(e, ClientError::Scene(_)), "{e}");

        let not_pem = scene_file("ca", "not a certificate");
        let e = status(
            &Endpoint {
                url: "https://127.0.0.1:1".into(),
                token: None,
                ca: Some(not_pem.clone()),
            },
            None,
        )
        .unwrap_err();
        assert!(matches!(e, ClientError::LocalFile { .. }), "{e}");
        assert!(
            e.to_string().contains(&not_pem.display().to_string()),
            "{e}"
        );

        for bad in ["127.0.0.1:47000", "ftp://x", "http://"] {
            let e = status(&server_args(bad, None), None).unwrap_err();
            assert!(matches!(e, ClientError::BadServer { .. }), "{bad}: {e}");
        }
    }

    #[test]
    fn a_non_json_answer_is_a_bad_answer() {
        let listener = std::net::TcpListener::bind("127.0.0.1:0").unwrap();
        let url = format!("http://{}", listener.local_addr().unwrap());
        let server = thread::spawn(move || {
            use std::io::{Read, Write};
            let (mut stream, _) = listener.accept().unwrap();
            stream
                .set_read_timeout(Some(Duration::from_secs(5)))
                .unwrap();
            let mut buf = [0u8; 4096];
            let _ = stream.read(&mut buf);
            let body = "<html>hello</html>";
            let _ = write!(
                stream,
                "HTTP/1.1 200 OK\r\nContent-Type: text/html\r\nContent-Length: {}\r\nConnection: close\r\n\r\n{body}",
                body.len()
            );
        });
        let e = cancel(&server_args(&url, None), 1).unwrap_err();
        assert!(matches!(e, ClientError::BadAnswer { .. }), "{e}");
        assert!(e.to_string().contains("is not a job"), "{e}");
        server.join().unwrap();
    }

    /// The API on `farm` merged into tonic's server, as the service serves it
    /// (HTTP/1.1 accepted; TLS with `identity` when given), until `stop` fires.
    fn serve_with_tonic(
        farm: Arc<Farm>,
        identity: Option<(String, String)>,
    ) -> (
        std::net::SocketAddr,
        tokio::sync::oneshot::Sender<()>,
        thread::JoinHandle<()>,
    ) {
        let listener = std::net::TcpListener::bind("127.0.0.1:0").unwrap();
        listener.set_nonblocking(true).unwrap();
        let addr = listener.local_addr().unwrap();
        let (stop, stopped) = tokio::sync::oneshot::channel::<()>();
        let thread = thread::spawn(move || {
            let runtime = tokio::runtime::Builder::new_current_thread()
                .enable_all()
                .build()
                .unwrap();
            runtime.block_on(async move {
                let listener = tokio::net::TcpListener::from_std(listener).unwrap();
                let mut server = tonic::transport::Server::builder().accept_http1(true);
                if let Some((cert, key)) = identity {
                    server = server
                        .tls_config(
                            tonic::transport::ServerTlsConfig::new()
                                .identity(tonic::transport::Identity::from_pem(cert, key)),
                        )
                        .unwrap();
                }
                let routes = tonic::service::Routes::from(crate::service::api::router(farm, None));
                server
                    .add_routes(routes)
                    .serve_with_incoming_shutdown(
                        tonic::transport::server::TcpIncoming::from(listener),
                        async move {
                            let _ = stopped.await;
                        },
                    )
                    .await
                    .unwrap();
            });
        });
        (addr, stop, thread)
    }

    #[test]
    fn https_with_a_private_ca_through_tonics_server() {
        let ca_key = rcgen::KeyPair::generate().unwrap();
        let mut ca_params = rcgen::CertificateParams::new(Vec::<String>::new()).unwrap();
        ca_params.is_ca = rcgen::IsCa::Ca(rcgen::BasicConstraints::Unconstrained);
        ca_params
            .distinguished_name
            .push(rcgen::DnType::CommonName, "test farm CA");
        let ca = rcgen::CertifiedIssuer::self_signed(ca_params, ca_key).unwrap();
        let key = rcgen::KeyPair::generate().unwrap();
        let cert = rcgen::CertificateParams::new(vec!["localhost".to_string()])
            .unwrap()
            .signed_by(&key, &ca)
            .unwrap();
        let ca_file = scene_file("tls-ca", &ca.pem());

        let farm = Arc::new(Farm::default());
        let (addr, stop, thread) =
            serve_with_tonic(farm.clone(), Some((cert.pem(), key.serialize_pem())));
        let url = format!("https://localhost:{}", addr.port());
        let with_ca = Endpoint {
            url: url.clone(),
            token: None,
            ca: Some(ca_file),
        };
        let scene = scene_file("tls-scene", "Scene()");
        assert_eq!(submit(&with_ca, &job(&scene).unwrap()).unwrap(), 1);
        assert_eq!(farm.jobs.lock().unwrap().len(), 1);
        // Without the CA the server's certificate is not trusted.
        let e = status(&server_args(&url, None), None).unwrap_err();
        assert!(matches!(e, ClientError::Unreachable { .. }), "{e}");
        let _ = stop.send(());
        thread.join().unwrap();

        // Plain HTTP/1.1 through tonic's server, and an unknown path's JSON 404.
        let (addr, stop, thread) = serve_with_tonic(farm, None);
        let url = format!("http://{addr}");
        let table = status(&server_args(&url, None), None).unwrap();
        assert!(table.contains("jobs: 1"), "{table}");
        let e = status(&server_args(&format!("{url}/prefix"), None), None).unwrap_err();
        assert!(matches!(e, ClientError::Refused { status: 404, .. }), "{e}");
        let _ = stop.send(());
        thread.join().unwrap();
    }

    #[test]
    fn etas_read_as_durations() {
        assert_eq!(format_eta(None), "-");
        assert_eq!(format_eta(Some(f64::NAN)), "-");
        assert_eq!(format_eta(Some(12.2)), "12s");
        assert_eq!(format_eta(Some(184.0)), "3m04s");
        assert_eq!(format_eta(Some(7500.0)), "2h05m");
    }

    #[test]
    fn the_table_fits_80_columns() {
        let job = JobView {
            id: 123,
            state: JobState::Failed,
            priority: -10,
            scene_name: "scenes/a/very/long/path/to/some/scene/file.ron".into(),
            out: "/x".into(),
            frames_done: 100,
            frames_total: 1000,
            units_done: 6400,
            units_total: 64000,
            eta_seconds: Some(5.0),
            error: Some(
                "the worker crashed\nrepeatedly, with a very long explanation that goes on and on"
                    .into(),
            ),
            outputs: vec![],
            require_tags: vec![],
            blocklisted: vec!["w1".into()],
        };
        let table = status_table(std::slice::from_ref(&job), &[]);
        assert!(
            table.lines().all(|l| l.chars().count() <= COLUMNS),
            "{table}"
        );
        assert!(table.contains("…/to/some/scene/file.ron"), "{table}");
        assert!(
            table.contains("job 123: the worker crashed repeatedly"),
            "{table}"
        );
        let narrow = JobView {
            id: 5,
            frames_total: 1,
            units_total: 64,
            scene_name: "fur.ron".into(),
            ..job.clone()
        };
        let table = status_table(&[narrow], &[]);
        assert!(
            table.lines().all(|l| l.chars().count() <= COLUMNS),
            "{table}"
        );
        assert!(
            table.contains("ERROR") && table.contains("fur.ron  the worker crashed repeatedly"),
            "{table}"
        );
        assert!(table.contains("workers: 0"));
        let details = job_details(&job);
        assert!(
            details.contains("blocklisted:  w1") && details.contains("outputs:      0"),
            "{details}"
        );
    }
}
