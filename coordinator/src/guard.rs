//! What a request must show before any route sees it, as pure functions of
//! its method, target and headers: the one parser of bearer tokens (the
//! gate, the HTTP API, the studio and the workers' gRPC calls all use
//! [`bearer`]), the studio's query token (read for `GET /studio/events`
//! only), and the `Host` and `Origin` checks that keep a browser from being
//! turned against the service.
//!
//! * **Tokens.** `Authorization: Bearer <token>`, the scheme in any case
//!   (RFC 9110 §11.1), compared in constant time ([`same_secret`]). A
//!   `?token=` in the query opens `GET /studio/events` and nothing else: an
//!   `EventSource` cannot send a header, and every other request of the
//!   page sends it, so a token in a URL reaches no other route (nor a
//!   proxy's access log for one).
//! * **Host.** Without a token a page on another site could reach the
//!   service by DNS rebinding (its name made to resolve to 127.0.0.1). So
//!   without a token only a `Host` naming this machine by a loopback address
//!   (`127.0.0.1`, `[::1]`, any port) or `localhost` is served, and the
//!   names given to `--allow-host`. With a token, the token is what a client
//!   must have, and `Host` is not restricted.
//! * **Origin.** A request that changes state (`POST`, `PUT`, `DELETE`,
//!   `PATCH`) with an `Origin` other than the service's own (its scheme
//!   aside, the same host and port as `Host`) is refused, token or not: a
//!   cross-site form cannot cancel a job or save the studio's scene.
//!   Browsers send `Origin` with every such request; the service's own
//!   clients (the CLI, the workers) send none.
//!
//! Jupyter makes the same two choices (a `Host` check against local names,
//! and a token even on localhost is its default); Jenkins asks for a CSRF
//! crumb where this service compares `Origin`.

use axum::http::{HeaderMap, Method, StatusCode, Uri, header};

/// The one route that takes its token from the query.
pub const EVENTS_PATH: &str = "/studio/events";

/// The token of an `Authorization` value of the `Bearer` scheme (in any
/// case, followed by spaces or tabs), trimmed; `None` for any other value.
pub fn bearer(value: &[u8]) -> Option<&[u8]> {
    const SCHEME: &[u8] = b"bearer";
    let (scheme, rest) = value.split_at_checked(SCHEME.len())?;
    if !scheme.eq_ignore_ascii_case(SCHEME) || !matches!(rest.first(), Some(b' ' | b'\t')) {
        return None;
    }
    Some(rest.trim_ascii())
}

/// Whether `given` equals `secret`, in a time that depends only on their lengths.
pub fn same_secret(given: &[u8], secret: &[u8]) -> bool {
    let mut diff = given.len() ^ secret.len();
    for i in 0..given.len().max(secret.len()) {
        let a = given.get(i).copied().unwrap_or(0);
        let b = secret.get(i).copied().unwrap_or(0);
        diff |= usize::from(a ^ b);
    }
    std::hint::black_box(diff) == 0
}

/// Whether an `Authorization` value (absent: `None`) carries `token`.
pub fn bearer_is(value: Option<&[u8]>, token: &[u8]) -> bool {
    value
        .and_then(bearer)
        .is_some_and(|given| same_secret(given, token))
}

/// The value of `name` in a query string, percent-decoded as a form
/// (`+` is a space; bytes that are not UTF-8 become U+FFFD). The first of
/// several wins.
pub fn query_param(query: &str, name: &str) -> Option<String> {
    form_urlencoded::parse(query.as_bytes())
        .find(|(k, _)| k == name)
        .map(|(_, v)| v.into_owned())
}

/// Whether a request carries `token`: in its `Authorization` header, or for
/// `GET /studio/events` alone, in its `token` query parameter.
pub fn admits(method: &Method, uri: &Uri, headers: &HeaderMap, token: &[u8]) -> bool {
    if bearer_is(
        headers.get(header::AUTHORIZATION).map(|v| v.as_bytes()),
        token,
    ) {
        return true;
    }
    *method == Method::GET
        && uri.path() == EVENTS_PATH
        && uri
            .query()
            .and_then(|q| query_param(q, "token"))
            .is_some_and(|given| same_secret(given.as_bytes(), token))
}

/// The host of an authority (`name`, `name:port`, `[v6]` or `[v6]:port`),
/// in lower case, brackets kept; `None` when it is not of that form.
pub fn host_name(authority: &str) -> Option<String> {
    let (host, port) = match authority.strip_prefix('[') {
        Some(inner) => {
            let (address, rest) = inner.split_once(']')?;
            let port = match rest {
                "" => None,
                rest => Some(rest.strip_prefix(':')?),
            };
            let address_ok = !address.is_empty()
                && address
                    .bytes()
                    .all(|b| b.is_ascii_hexdigit() || b == b':' || b == b'.');
            (address_ok.then_some(&authority[..address.len() + 2])?, port)
        }
        None => {
            let (host, port) = match authority.split_once(':') {
                Some((host, port)) => (host, Some(port)),
                None => (authority, None),
            };
            let host_ok = !host.is_empty()
                && host
                    .bytes()
                    .all(|b| b.is_ascii_alphanumeric() || b"-._~".contains(&b));
            (host_ok.then_some(host)?, port)
        }
    };
    let port_ok = port.is_none_or(|p| {
        !p.is_empty()
            && p.len() <= 5
            && p.bytes().all(|b| b.is_ascii_digit())
            && p.parse::<u16>().is_ok()
    });
    port_ok.then(|| host.to_ascii_lowercase())
}

/// Whether a host name (as [`host_name`] gives it) names this machine:
/// `localhost` or a loopback address.
pub fn is_loopback_name(host: &str) -> bool {
    if host == "localhost" {
        return true;
    }
    let literal = host
        .strip_prefix('[')
        .and_then(|h| h.strip_suffix(']'))
        .unwrap_or(host);
    literal
        .parse::<std::net::IpAddr>()
        .is_ok_and(|ip| ip.is_loopback() && (host.starts_with('[') || ip.is_ipv4()))
}

/// Whether `method` may change state (and so is refused from a foreign origin).
pub fn changes_state(method: &Method) -> bool {
    matches!(
        *method,
        Method::POST | Method::PUT | Method::DELETE | Method::PATCH
    )
}

/// A request refused by [`Hosts::check`]: the status and a one-line message.
#[derive(Clone, Debug, PartialEq)]
pub struct Refused {
    /// 400 (no `Host`) or 403.
    pub status: StatusCode,
    /// What was refused and how to be served.
    pub message: String,
}

/// The `Host` and `Origin` rules of a service.
#[derive(Clone, Debug, Default)]
pub struct Hosts {
    /// Names served besides loopback ones (`--allow-host`), in lower case.
    allowed: Vec<String>,
    /// Whether the service has a token (then `Host` is not restricted).
    token: bool,
}

impl Hosts {
    /// The rules of a service with or without a token that serves the
    /// names `allowed` besides loopback ones.
    pub fn new(allowed: &[String], token: bool) -> Hosts {
        Hosts {
            allowed: allowed.iter().map(|n| n.to_ascii_lowercase()).collect(),
            token,
        }
    }

    fn allows(&self, host: &str) -> bool {
        is_loopback_name(host) || self.allowed.iter().any(|a| a == host)
    }

    /// Checks a request's `Host` (and an HTTP/2 `:authority`, which `uri`
    /// holds) and, when it changes state, its `Origin`.
    pub fn check(&self, method: &Method, uri: &Uri, headers: &HeaderMap) -> Result<(), Refused> {
        let forbidden = |message: String| Refused {
            status: StatusCode::FORBIDDEN,
            message,
        };
        let host_header = headers.get(header::HOST).map(|v| v.as_bytes());
        let authority = uri
            .authority()
            .map(|a| a.as_str().as_bytes())
            .or(host_header);
        if !self.token {
            let Some(authority) = authority else {
                return Err(Refused {
                    status: StatusCode::BAD_REQUEST,
                    message: "a request without Host: name the service as 127.0.0.1, \
                              localhost or [::1] (or start it with --token)"
                        .into(),
                });
            };
            for value in [Some(authority), host_header].into_iter().flatten() {
                let name = std::str::from_utf8(value).ok().and_then(host_name);
                if !name.as_deref().is_some_and(|n| self.allows(n)) {
                    let shown = shown(value);
                    let hint = name.map_or_else(String::new, |n| {
                        format!("; start it with --allow-host {n} to serve that name")
                    });
                    return Err(forbidden(format!(
                        "Host \"{shown}\" is not served: without a token this service answers \
                         only to 127.0.0.1, localhost and [::1] (a page elsewhere could reach it \
                         by DNS rebinding){hint}, or with --token"
                    )));
                }
            }
        }
        if changes_state(method)
            && let Some(origin) = headers.get(header::ORIGIN).map(|v| v.as_bytes())
            && !same_origin(origin, authority)
        {
            return Err(forbidden(format!(
                "{method} from the page of Origin \"{}\" refused: requests that change \
                 state are taken from this service's own pages only (Origin must name \
                 Host \"{}\")",
                shown(origin),
                authority.map_or_else(String::new, shown)
            )));
        }
        Ok(())
    }
}

/// Whether an `Origin` value names the same host and port as `authority`
/// (the scheme aside: the service's own pages come from its one port).
fn same_origin(origin: &[u8], authority: Option<&[u8]>) -> bool {
    let Some(authority) = authority else {
        return false;
    };
    let Ok(origin) = std::str::from_utf8(origin) else {
        return false;
    };
    let Some((_, rest)) = origin.split_once("://") else {
        return false;
    };
    rest.as_bytes().eq_ignore_ascii_case(authority)
}

/// A header value for a message: printable ASCII, at most 100 characters.
fn shown(value: &[u8]) -> String {
    let text: String = value
        .iter()
        .take(100)
        .map(|&b| {
            if (b' '..=b'~').contains(&b) && b != b'"' && b != b'\\' {
                char::from(b)
            } else {
                '?'
            }
        })
        .collect();
    if value.len() > 100 {
        format!("{text}…")
    } else {
        text
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_bearer_scheme_is_read_in_any_case() {
        assert_eq!(bearer(b"Bearer s3cret"), Some(&b"s3cret"[..]));
        assert_eq!(bearer(b"bearer s3cret"), Some(&b"s3cret"[..]));
        assert_eq!(bearer(b"BEARER \t s3cret "), Some(&b"s3cret"[..]));
        assert_eq!(bearer(b"Bearers3cret"), None);
        assert_eq!(bearer(b"Basic czNjcmV0"), None);
        assert_eq!(bearer(b"Bear"), None);
        assert_eq!(bearer("Bearé s3cret".as_bytes()), None);
        assert!(bearer_is(Some(b"bEaReR s3cret"), b"s3cret"));
        assert!(!bearer_is(Some(b"Bearer s3cre"), b"s3cret"));
        assert!(!bearer_is(None, b"s3cret"));
    }

    #[test]
    fn secrets_compare_whole() {
        assert!(same_secret(b"abc", b"abc"));
        assert!(!same_secret(b"abc", b"abd"));
        assert!(!same_secret(b"ab", b"abc"));
        assert!(!same_secret(b"abcd", b"abc"));
        assert!(!same_secret(b"", b"abc"));
        assert!(same_secret(b"", b""));
    }

    #[test]
    fn query_parameters_are_decoded_whatever_the_bytes() {
        assert_eq!(
            query_param("a=1&token=s%3Dx", "token").as_deref(),
            Some("s=x")
        );
        assert_eq!(query_param("a=1", "token"), None);
        assert_eq!(query_param("token=a+b", "token").as_deref(), Some("a b"));
        // `%` followed within two bytes by a character of several bytes.
        assert_eq!(
            query_param("token=%a\u{e9}xx", "token").as_deref(),
            Some("%a\u{e9}xx")
        );
        assert_eq!(
            query_param("token=%C3%A9%ff", "token").as_deref(),
            Some("\u{e9}\u{fffd}")
        );
        assert_eq!(query_param("token=%", "token").as_deref(), Some("%"));
    }

    #[test]
    fn a_query_token_opens_the_event_stream_only() {
        let admits = |method: Method, uri: &str, authorization: Option<&str>| {
            let mut headers = HeaderMap::new();
            if let Some(a) = authorization {
                headers.insert(header::AUTHORIZATION, a.parse().unwrap());
            }
            admits(&method, &uri.parse().unwrap(), &headers, b"s3cret")
        };
        assert!(admits(Method::GET, "/studio/events?token=s3cret", None));
        assert!(admits(Method::GET, "/studio/events?x=1&token=s3cret", None));
        assert!(!admits(Method::GET, "/studio/events?token=nope", None));
        assert!(!admits(Method::POST, "/studio/events?token=s3cret", None));
        for uri in [
            "/studio/scene?token=s3cret",
            "/studio/tiles?generation=1&from=0&to=1&token=s3cret",
            "/studio/save?token=s3cret",
            "/api/v1/jobs?token=s3cret",
            "/metrics?token=s3cret",
        ] {
            assert!(!admits(Method::GET, uri, None), "{uri}");
            assert!(!admits(Method::POST, uri, None), "{uri}");
            assert!(admits(Method::GET, uri, Some("bearer s3cret")), "{uri}");
        }
    }

    #[test]
    fn host_names_are_parsed_and_checked() {
        assert_eq!(host_name("localhost:47000").as_deref(), Some("localhost"));
        assert_eq!(host_name("LocalHost").as_deref(), Some("localhost"));
        assert_eq!(host_name("[::1]:8080").as_deref(), Some("[::1]"));
        assert_eq!(host_name("[::1]").as_deref(), Some("[::1]"));
        assert_eq!(host_name("127.0.0.1:1").as_deref(), Some("127.0.0.1"));
        for bad in [
            "", ":80", "a:", "a:b", "a:99999", "a:1:2", "::1", "[::1", "[::1]x", "a b", "u@host",
            "h\u{e9}",
        ] {
            assert_eq!(host_name(bad), None, "{bad:?}");
        }
        for local in ["localhost", "127.0.0.1", "127.0.0.2", "[::1]"] {
            assert!(is_loopback_name(local), "{local}");
        }
        for foreign in [
            "example.org",
            "10.0.0.1",
            "[::2]",
            "::1",
            "localhost.example.org",
        ] {
            assert!(!is_loopback_name(foreign), "{foreign}");
        }
    }

    fn request(method: Method, uri: &str, headers: &[(&str, &[u8])]) -> (Method, Uri, HeaderMap) {
        let mut map = HeaderMap::new();
        for (name, value) in headers {
            map.append(
                axum::http::HeaderName::from_bytes(name.as_bytes()).unwrap(),
                axum::http::HeaderValue::from_bytes(value).unwrap(),
            );
        }
        (method, uri.parse().unwrap(), map)
    }

    #[test]
    fn without_a_token_only_local_and_allowed_hosts_are_served() {
        let hosts = Hosts::new(&["Farm.LAN".to_string()], false);
        let check = |host: Option<&[u8]>| {
            let headers: Vec<(&str, &[u8])> = host.into_iter().map(|h| ("host", h)).collect();
            let (m, u, h) = request(Method::GET, "/api/v1/jobs", &headers);
            hosts.check(&m, &u, &h)
        };
        for ok in [
            &b"127.0.0.1:47000"[..],
            b"127.0.0.1",
            b"localhost:47000",
            b"[::1]:47000",
            b"farm.lan:47000",
        ] {
            assert_eq!(check(Some(ok)), Ok(()), "{}", String::from_utf8_lossy(ok));
        }
        let refused = check(Some(b"evil.example:47000")).unwrap_err();
        assert_eq!(refused.status, StatusCode::FORBIDDEN);
        assert!(
            refused.message.contains("evil.example:47000")
                && refused.message.contains("--allow-host evil.example"),
            "{}",
            refused.message
        );
        assert_eq!(
            check(Some(b"\xff\xfe")).unwrap_err().status,
            StatusCode::FORBIDDEN
        );
        assert_eq!(check(None).unwrap_err().status, StatusCode::BAD_REQUEST);
        // An HTTP/2 request names its host in `:authority` (the URI).
        let (m, u, h) = request(Method::GET, "http://evil.example:1/metrics", &[]);
        assert!(hosts.check(&m, &u, &h).is_err());
        let (m, u, h) = request(Method::GET, "http://127.0.0.1:1/metrics", &[]);
        assert_eq!(hosts.check(&m, &u, &h), Ok(()));
        // With a token any Host is served.
        let (m, u, h) = request(Method::GET, "/", &[("host", b"evil.example")]);
        assert_eq!(Hosts::new(&[], true).check(&m, &u, &h), Ok(()));
    }

    #[test]
    fn a_foreign_origin_cannot_change_state_token_or_not() {
        for token in [false, true] {
            let hosts = Hosts::new(&[], token);
            let check = |method: Method, origin: Option<&[u8]>| {
                let mut headers: Vec<(&str, &[u8])> = vec![("host", b"127.0.0.1:47000")];
                headers.extend(origin.map(|o| ("origin", o)));
                let (m, u, h) = request(method, "/api/v1/jobs/1/cancel", &headers);
                hosts.check(&m, &u, &h)
            };
            for method in [Method::POST, Method::PUT, Method::DELETE, Method::PATCH] {
                let refused = check(method.clone(), Some(b"http://evil.example")).unwrap_err();
                assert_eq!(refused.status, StatusCode::FORBIDDEN);
                assert!(
                    refused.message.contains("http://evil.example"),
                    "{}",
                    refused.message
                );
                assert!(check(method.clone(), Some(b"null")).is_err());
                assert!(check(method.clone(), Some(b"http://127.0.0.1:47001")).is_err());
                assert_eq!(
                    check(method.clone(), Some(b"http://127.0.0.1:47000")),
                    Ok(())
                );
                assert_eq!(check(method.clone(), None), Ok(()));
            }
            assert_eq!(check(Method::GET, Some(b"http://evil.example")), Ok(()));
        }
    }
}
