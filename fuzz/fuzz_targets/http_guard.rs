//! Any bytes as the parts of an HTTP request that the service reads itself
//! before a route does (`coordinator::guard`): the bearer token, the query's
//! percent-decoding, the event stream's query token, the `Host` and `Origin`
//! checks. None may panic, whatever the bytes.
#![no_main]

use coordinator::guard;
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    let _ = guard::bearer(data);
    let _ = guard::bearer_is(Some(data), b"s3cret");
    let text = String::from_utf8_lossy(data);
    let _ = guard::query_param(&text, "token");
    if let Some(name) = guard::host_name(&text) {
        let _ = guard::is_loopback_name(&name);
    }
    // NUL-separated: request target, Host, Origin, Authorization.
    let mut parts = data.split(|&b| b == 0);
    let target = parts.next().unwrap_or_default();
    let Ok(uri) = http::Uri::try_from(target) else {
        return;
    };
    let mut headers = http::HeaderMap::new();
    for name in [
        http::header::HOST,
        http::header::ORIGIN,
        http::header::AUTHORIZATION,
    ] {
        if let Some(value) = parts
            .next()
            .and_then(|v| http::HeaderValue::from_bytes(v).ok())
        {
            headers.insert(name, value);
        }
    }
    for method in [http::Method::GET, http::Method::POST] {
        let _ = guard::admits(&method, &uri, &headers, b"s3cret");
        for token in [false, true] {
            let hosts = guard::Hosts::new(&["farm.lan".to_string()], token);
            let _ = hosts.check(&method, &uri, &headers);
        }
    }
});
