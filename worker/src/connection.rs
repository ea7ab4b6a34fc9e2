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

#[cfg(test)]
mod tests {
    use super::*;

    fn config(coordinator: &str, ca: Option<&[u8]>, token: Option<&str>) -> WorkerConfig {
        WorkerConfig {
            token: token.map(str::to_string),
            ca: ca.map(<[u8]>::to_vec),
            ..crate::testing::config(coordinator)
        }
    }

    /// The message of the address error `endpoint` gives for `config`.
    fn refused(config: &WorkerConfig) -> String {
        match endpoint(config) {
            Err(WorkerError::Address { url, message }) => {
                assert_eq!(url, config.coordinator);
                message
            }
            Err(e) => panic!("another error: {e}"),
            Ok(_) => panic!("{} was accepted", config.coordinator),
        }
    }

    #[test]
    fn an_address_needs_a_scheme_a_host_and_tls_with_its_ca() {
        assert!(endpoint(&config("http://127.0.0.1:50051", None, None)).is_ok());
        assert_eq!(
            refused(&config("ftp://127.0.0.1:50051", None, None)),
            "expected http://HOST:PORT or https://HOST:PORT"
        );
        assert_eq!(
            refused(&config("http://127.0.0.1:50051", Some(b"PEM"), None)),
            "--ca needs an https:// address"
        );
        assert_eq!(
            refused(&config("https://127.0.0.1:50051", None, None)),
            "https:// needs --ca FILE to verify the coordinator"
        );
        assert!(!refused(&config("not a url", None, None)).is_empty());
    }

    #[test]
    fn a_token_is_sent_as_a_bearer_and_must_be_printable_ascii() {
        let Auth(none) = Auth::bearer(&config("http://h:1", None, None)).unwrap();
        assert!(none.is_none());
        let Auth(value) = Auth::bearer(&config("http://h:1", None, Some("s3cret"))).unwrap();
        assert_eq!(value.unwrap().to_str().unwrap(), "Bearer s3cret");
        match Auth::bearer(&config("http://h:1", None, Some("line\nbreak"))) {
            Err(WorkerError::Address { message, .. }) => {
                assert_eq!(message, "the token must be printable ASCII")
            }
            other => panic!("expected an address error, got {:?}", other.err()),
        }
    }

    #[test]
    fn the_backoff_doubles_to_five_seconds_and_starts_again() {
        let mut backoff = Backoff::new();
        let waits: Vec<u128> = (0..9).map(|_| backoff.next().as_millis()).collect();
        assert_eq!(waits, [100, 200, 400, 800, 1600, 3200, 5000, 5000, 5000]);
        backoff.reset();
        assert_eq!(backoff.next(), Duration::from_millis(100));
    }

    #[test]
    fn only_refusals_of_the_worker_are_for_good() {
        for code in [
            Code::Unauthenticated,
            Code::PermissionDenied,
            Code::FailedPrecondition,
        ] {
            assert!(is_refusal(&Status::new(code, "no")), "{code:?}");
        }
        for code in [
            Code::Unavailable,
            Code::NotFound,
            Code::InvalidArgument,
            Code::Internal,
        ] {
            assert!(!is_refusal(&Status::new(code, "no")), "{code:?}");
        }
    }

    #[test]
    fn what_the_coordinator_says_is_escaped_and_capped() {
        assert_eq!(said(&Status::internal("two\nlines")), "two\\nlines");
        let long = "x".repeat(convert::MAX_REASON_CHARS + 10);
        assert_eq!(
            shown(&long).chars().count(),
            convert::MAX_REASON_CHARS + 1,
            "capped, with an ellipsis"
        );
    }

    #[test]
    fn an_error_chain_is_one_line_of_causes() {
        #[derive(Debug)]
        struct Outer(std::io::Error);
        impl std::fmt::Display for Outer {
            fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
                f.write_str("cannot connect")
            }
        }
        impl std::error::Error for Outer {
            fn source(&self) -> Option<&(dyn std::error::Error + 'static)> {
                Some(&self.0)
            }
        }
        let e = Outer(std::io::Error::other("connection refused"));
        assert_eq!(error_chain(&e), "cannot connect: connection refused");
    }

    #[tokio::test]
    async fn a_sleep_ends_early_when_asked_to_stop() {
        let (tell, mut stop) = watch::channel(false);
        assert!(!sleep_or_stop(Duration::from_millis(1), &mut stop).await);
        let started = std::time::Instant::now();
        let told = tokio::spawn(async move {
            tokio::time::sleep(Duration::from_millis(20)).await;
            tell.send(true).unwrap();
            tell
        });
        assert!(sleep_or_stop(Duration::from_secs(600), &mut stop).await);
        assert!(started.elapsed() < Duration::from_secs(60));
        assert!(
            sleep_or_stop(Duration::from_secs(600), &mut stop).await,
            "already stopped"
        );
        drop(told.await.unwrap());
    }
}
