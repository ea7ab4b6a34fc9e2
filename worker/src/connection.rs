//! The connection to the coordinator: its address and TLS, the bearer token
//! on every call, the backoff between attempts, and how its refusals and
//! messages are read.

use std::time::Duration;

use hypertexture_proto::MAX_MESSAGE_BYTES;
use hypertexture_proto::convert;
use hypertexture_proto::pb::farm_client::FarmClient;
use tokio::sync::watch;
use tonic::transport::{Certificate, Channel, ClientTlsConfig, Endpoint};
use tonic::{Code, Status};

use crate::{WorkerConfig, WorkerError, body};

/// The farm's client as a worker holds it: the bearer token on every call,
/// request bodies that end with their last message.
pub(crate) type Client = FarmClient<
    tonic::service::interceptor::InterceptedService<body::EndStreamEarly<Channel>, Auth>,
>;

/// A client of the farm on `channel`, with `auth` on every call.
pub(crate) fn client(channel: Channel, auth: Auth) -> Client {
    FarmClient::with_interceptor(body::EndStreamEarly(channel), auth)
        .max_decoding_message_size(MAX_MESSAGE_BYTES)
        .max_encoding_message_size(MAX_MESSAGE_BYTES)
}

/// Adds `authorization: Bearer <token>` to every call.
#[derive(Clone)]
pub struct Auth(Option<tonic::metadata::MetadataValue<tonic::metadata::Ascii>>);

impl tonic::service::Interceptor for Auth {
    fn call(&mut self, mut request: tonic::Request<()>) -> Result<tonic::Request<()>, Status> {
        if let Some(value) = &self.0 {
            request
                .metadata_mut()
                .insert(hypertexture_proto::AUTHORIZATION, value.clone());
        }
        Ok(request)
    }
}

impl Auth {
    /// `Bearer <token>` for the farm's shared secret, if `config` has one.
    pub(crate) fn bearer(config: &WorkerConfig) -> Result<Auth, WorkerError> {
        Ok(Auth(match &config.token {
            Some(t) => Some(
                format!("Bearer {t}")
                    .parse()
                    .map_err(|_| WorkerError::Address {
                        url: config.coordinator.clone(),
                        message: "the token must be printable ASCII".into(),
                    })?,
            ),
            None => None,
        }))
    }
}

/// Exponential backoff between reconnection attempts: 100 ms doubling to 5 s.
pub(crate) struct Backoff(Duration);

impl Backoff {
    const FIRST: Duration = Duration::from_millis(100);
    const MAX: Duration = Duration::from_secs(5);

    /// A backoff at its first wait.
    pub(crate) fn new() -> Backoff {
        Backoff(Self::FIRST)
    }

    pub(crate) fn next(&mut self) -> Duration {
        let now = self.0;
        self.0 = (self.0 * 2).min(Self::MAX);
        now
    }

    pub(crate) fn reset(&mut self) {
        self.0 = Self::FIRST;
    }
}

/// Sleeps for `d` unless asked to stop first; returns whether to stop.
pub(crate) async fn sleep_or_stop(d: Duration, stop: &mut watch::Receiver<bool>) -> bool {
    if *stop.borrow() {
        return true;
    }
    tokio::select! {
        _ = tokio::time::sleep(d) => *stop.borrow(),
        r = stop.changed() => r.is_err() || *stop.borrow(),
    }
}

/// The endpoint for the coordinator URL, with TLS when it is https.
pub(crate) fn endpoint(config: &WorkerConfig) -> Result<Endpoint, WorkerError> {
    let bad = |message: String| WorkerError::Address {
        url: config.coordinator.clone(),
        message,
    };
    let mut endpoint = Endpoint::from_shared(config.coordinator.clone())
        .map_err(|e| bad(e.to_string()))?
        .connect_timeout(Duration::from_secs(5))
        .timeout(Duration::from_secs(60))
        .tcp_nodelay(true);
    let uri = endpoint.uri().clone();
    match (uri.scheme_str(), &config.ca) {
        (Some("http"), None) => {}
        (Some("http"), Some(_)) => return Err(bad("--ca needs an https:// address".into())),
        (Some("https"), Some(ca)) => {
            let tls = ClientTlsConfig::new().ca_certificate(Certificate::from_pem(ca));
            endpoint = endpoint.tls_config(tls).map_err(|e| bad(e.to_string()))?;
        }
        (Some("https"), None) => {
            return Err(bad(
                "https:// needs --ca FILE to verify the coordinator".into()
            ));
        }
        _ => return Err(bad("expected http://HOST:PORT or https://HOST:PORT".into())),
    }
    if uri.host().is_none() {
        return Err(bad("no host".into()));
    }
    Ok(endpoint)
}

/// An error with its causes, on one line.
pub(crate) fn error_chain(e: &dyn std::error::Error) -> String {
    let mut s = e.to_string();
    let mut source = e.source();
    while let Some(cause) = source {
        s.push_str(": ");
        s.push_str(&cause.to_string());
        source = cause.source();
    }
    s
}

/// What the coordinator said, safe to log: a message off the network is
/// escaped and capped like every other ([`convert::untrusted`]).
pub(crate) fn said(status: &Status) -> String {
    shown(status.message())
}

/// A string that came from the coordinator (a scene's name, a file's path,
/// a message that holds them), safe to log: escaped and capped as the
/// coordinator logs what workers send ([`convert::untrusted`]).
pub(crate) fn shown(s: &str) -> String {
    convert::untrusted(s, convert::MAX_REASON_CHARS)
}

/// Refusals that retrying cannot fix.
pub(crate) fn is_refusal(status: &Status) -> bool {
    matches!(
        status.code(),
        Code::Unauthenticated | Code::PermissionDenied | Code::FailedPrecondition
    )
}
