//! HTTP requests to a running service through `ureq`: every status is an
//! answer (4xx and 5xx included), read whole.

use std::time::{Duration, Instant};

/// An HTTP answer: status, headers, body.
pub struct Answer {
    pub status: u16,
    pub headers: ureq::http::HeaderMap,
    pub body: String,
}

impl Answer {
    /// The body as JSON.
    pub fn json(&self) -> serde_json::Value {
        serde_json::from_str(&self.body).unwrap_or_else(|e| panic!("{e}: {}", self.body))
    }

    /// The `error` of a JSON error body.
    pub fn error(&self) -> String {
        self.json()["error"]
            .as_str()
            .unwrap_or_default()
            .to_string()
    }
}

/// The answer `result` holds, whatever its status.
pub fn answer(result: Result<ureq::http::Response<ureq::Body>, ureq::Error>) -> Answer {
    let mut response = result.expect("the service answers");
    Answer {
        status: response.status().as_u16(),
        headers: response.headers().clone(),
        body: response.body_mut().read_to_string().unwrap_or_default(),
    }
}

/// `POST /api/v1/jobs` with `body` as JSON.
pub fn post_job(url: &str, body: &serde_json::Value) -> Answer {
    post(url, "/api/v1/jobs", body)
}

/// `POST path` with `body` as JSON.
pub fn post(url: &str, path: &str, body: &serde_json::Value) -> Answer {
    answer(
        ureq::post(&format!("{url}{path}"))
            .config()
            .http_status_as_error(false)
            .build()
            .send_json(body),
    )
}

/// `GET path`.
pub fn get(url: &str, path: &str) -> Answer {
    answer(
        ureq::get(&format!("{url}{path}"))
            .config()
            .http_status_as_error(false)
            .build()
            .call(),
    )
}

/// Polls `GET path` (at most `secs`) until `until` holds of its answer.
pub fn poll(url: &str, path: &str, secs: u64, until: impl Fn(&Answer) -> bool) -> Answer {
    let deadline = Instant::now() + Duration::from_secs(secs);
    loop {
        let a = get(url, path);
        if until(&a) {
            return a;
        }
        assert!(
            Instant::now() < deadline,
            "{path} after {secs} s: {} {}",
            a.status,
            a.body
        );
        std::thread::sleep(Duration::from_millis(50));
    }
}
