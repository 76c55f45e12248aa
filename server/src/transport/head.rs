//! The check of a request head: its limits, its syntax and its body framing.

/// Longest request head (request line and headers) accepted ([`HeadError::HeadTooLarge`]).
pub const MAX_HEAD_BYTES: usize = 64 * 1024;
/// Longest request line (method, URI, version) accepted ([`HeadError::UriTooLong`]).
pub const MAX_REQUEST_LINE_BYTES: usize = 8 * 1024;
/// Most headers in one request ([`HeadError::TooManyHeaders`]).
pub const MAX_HEADERS: usize = 100;

/// Why a request head was refused.
///
/// The transport says only what is wrong with the head; how that is answered (a status, a JSON
/// error code) is the HTTP layer's decision, in `http::error`, like every other refusal. The
/// messages are the ones clients read in the answer's `message`.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum HeadError {
    /// The head does not parse, or holds what hyper would refuse after parsing it: a bad
    /// method or URI, a bad or conflicting `Content-Length`, a `Transfer-Encoding` that does
    /// not end with `chunked` or comes in HTTP/1.0.
    #[error("the request head could not be read: {0}")]
    Malformed(String),
    /// The request line is longer than [`MAX_REQUEST_LINE_BYTES`].
    #[error("the request line exceeds {MAX_REQUEST_LINE_BYTES} bytes")]
    UriTooLong,
    /// The head is longer than [`MAX_HEAD_BYTES`].
    #[error("the request head exceeds {MAX_HEAD_BYTES} bytes")]
    HeadTooLarge,
    /// The head has more than [`MAX_HEADERS`] headers.
    #[error("the request has more than {MAX_HEADERS} headers")]
    TooManyHeaders,
}

/// What the gate passes to hyper after a head.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(super) enum Framing {
    /// A body of this many bytes (0: none), then the next head.
    Length(u64),
    /// A chunked body: the rest of the connection passes unchecked.
    Chunked,
}

/// The method of the stand-in request; the gate refuses it from clients, so only a stand-in
/// carries it.
pub(super) const STAND_IN_METHOD: &str = "SPLATD-REFUSED-HEAD";
/// What hyper reads in place of a refused head: a request the service answers with the refusal
/// (which the gate may have found while hyper still had earlier requests to answer).
pub(super) const STAND_IN: &[u8] = b"SPLATD-REFUSED-HEAD / HTTP/1.1\r\nconnection: close\r\n\r\n";

/// Checks the request head at the start of `buf`: `Ok(None)` while it is incomplete (and within
/// the limits), its length and body framing once complete, or the refusal to answer.
pub(super) fn check_head(buf: &[u8]) -> Result<Option<(usize, Framing)>, HeadError> {
    let mut headers = [httparse::EMPTY_HEADER; MAX_HEADERS];
    let mut request = httparse::Request::new(&mut headers);
    let len = match request.parse(buf) {
        Ok(httparse::Status::Complete(len)) => len,
        Ok(httparse::Status::Partial) => {
            let line_end = buf.iter().position(|&b| b == b'\n');
            if line_end.unwrap_or(buf.len()) > MAX_REQUEST_LINE_BYTES {
                return Err(HeadError::UriTooLong);
            }
            if buf.len() > MAX_HEAD_BYTES {
                return Err(HeadError::HeadTooLarge);
            }
            return Ok(None);
        }
        Err(httparse::Error::TooManyHeaders) => return Err(HeadError::TooManyHeaders),
        Err(e) => return Err(HeadError::Malformed(format!("{e}"))),
    };
    let line_end = buf.iter().position(|&b| b == b'\n').unwrap_or(len);
    if line_end > MAX_REQUEST_LINE_BYTES {
        return Err(HeadError::UriTooLong);
    }
    if len > MAX_HEAD_BYTES {
        return Err(HeadError::HeadTooLarge);
    }
    // What hyper would refuse after parsing, refused here with a body instead.
    let method = request.method.unwrap_or_default();
    axum::http::Method::from_bytes(method.as_bytes())
        .ok()
        .filter(|m| m.as_str() != STAND_IN_METHOD)
        .ok_or_else(|| HeadError::Malformed(format!("invalid method {method:?}")))?;
    let path = request.path.unwrap_or_default();
    axum::http::Uri::try_from(path)
        .map_err(|e| HeadError::Malformed(format!("invalid URI: {e}")))?;
    let mut length: Option<u64> = None;
    let mut chunked = false;
    for h in request.headers.iter() {
        if h.name.eq_ignore_ascii_case("content-length") {
            for value in h.value.split(|&b| b == b',') {
                let parsed = std::str::from_utf8(value)
                    .ok()
                    .map(str::trim)
                    .filter(|v| !v.is_empty() && v.bytes().all(|b| b.is_ascii_digit()))
                    .and_then(|v| v.parse::<u64>().ok())
                    .ok_or_else(|| HeadError::Malformed("invalid Content-Length".into()))?;
                if length.is_some_and(|l| l != parsed) {
                    return Err(HeadError::Malformed(
                        "conflicting Content-Length headers".into(),
                    ));
                }
                length = Some(parsed);
            }
        } else if h.name.eq_ignore_ascii_case("transfer-encoding") {
            let last = h
                .value
                .rsplit(|&b| b == b',')
                .next()
                .map(|v| v.trim_ascii())
                .unwrap_or_default();
            if !last.eq_ignore_ascii_case(b"chunked") {
                return Err(HeadError::Malformed(
                    "a Transfer-Encoding must end with chunked".into(),
                ));
            }
            if request.version == Some(0) {
                return Err(HeadError::Malformed(
                    "Transfer-Encoding is not allowed in HTTP/1.0".into(),
                ));
            }
            chunked = true;
        }
    }
    let framing = if chunked {
        Framing::Chunked
    } else {
        Framing::Length(length.unwrap_or(0))
    };
    Ok(Some((len, framing)))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn heads_are_checked_like_hyper_would_but_answered_with_a_body() {
        let ok = b"POST /v1/frames/f/samples HTTP/1.1\r\nhost: x\r\ncontent-length: 5\r\n\r\nhello";
        assert_eq!(
            check_head(ok).unwrap(),
            Some((ok.len() - 5, Framing::Length(5)))
        );
        assert_eq!(check_head(&ok[..20]).unwrap(), None, "incomplete");
        let bare_lf = b"GET / HTTP/1.1\nhost: x\n\n";
        assert_eq!(
            check_head(bare_lf).unwrap(),
            Some((bare_lf.len(), Framing::Length(0)))
        );
        let chunked = b"POST / HTTP/1.1\r\ntransfer-encoding: chunked\r\n\r\n";
        assert_eq!(check_head(chunked).unwrap().unwrap().1, Framing::Chunked);

        let code = |head: &[u8]| match check_head(head).unwrap_err() {
            HeadError::Malformed(_) => "malformed",
            HeadError::UriTooLong => "uri too long",
            HeadError::HeadTooLarge => "head too large",
            HeadError::TooManyHeaders => "too many headers",
        };
        assert_eq!(code(b"GET / HTTP/1.1\r\nbad header\r\n\r\n"), "malformed");
        assert_eq!(
            code(b"GET / HTTP/1.1\r\ncontent-length: 5\r\ncontent-length: 6\r\n\r\n"),
            "malformed"
        );
        assert_eq!(
            code(b"POST / HTTP/1.1\r\ntransfer-encoding: gzip\r\n\r\n"),
            "malformed"
        );
        let long_uri = format!("GET /{} HTTP/1.1\r\n", "a".repeat(MAX_REQUEST_LINE_BYTES));
        assert_eq!(code(long_uri.as_bytes()), "uri too long");
        let many: String = (0..=MAX_HEADERS).map(|i| format!("x-{i}: 1\r\n")).collect();
        assert_eq!(
            code(format!("GET / HTTP/1.1\r\n{many}\r\n").as_bytes()),
            "too many headers"
        );
        let big = format!("GET / HTTP/1.1\r\nx: {}\r\n", "b".repeat(MAX_HEAD_BYTES));
        assert_eq!(code(big.as_bytes()), "head too large");
    }
}
