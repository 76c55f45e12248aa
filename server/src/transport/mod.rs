//! Connections: how many may be open, how long each may take to say what it wants and to take
//! its answer, and what a client hears when its request head cannot be read.
//!
//! * [`Connections`] caps open connections (`--max-connections`). At the cap, a new connection
//!   first pushes out the oldest one that has no request in progress, preferring one that never
//!   sent a complete request head (a silent or trickling socket) over an idle keep-alive one; if
//!   every connection is serving a request, the new one is closed at once. Silent sockets
//!   therefore cannot lock out `/healthz` or a worker, and connections with work in progress are
//!   never touched.
//! * [`HeadGate`] sits between the socket and hyper and reads every request head itself before
//!   hyper sees a byte of it: the head must be complete within `--head-timeout` (from accept for
//!   the first request, from its first byte for the next ones on a keep-alive connection, which
//!   may idle for `--idle-timeout` before that byte), within [`MAX_HEAD_BYTES`], with a request
//!   line within [`MAX_REQUEST_LINE_BYTES`] and at most [`MAX_HEADERS`] headers, and parse. A head
//!   that breaks a rule is refused with a [`HeadError`], answered as `http::error` maps it (a
//!   JSON `ErrorBody`) with `Connection: close` (hyper's own answers to such heads have no
//!   body), through the same service as every other answer, so responses stay in order.
//! * A response must be handed to the socket within `--response-timeout` from its first byte:
//!   a client that stops reading is disconnected and the response's memory freed.
//!
//! The gate passes a request body with a `Content-Length` through byte for byte and then expects
//! the next head; after a chunked body it cannot tell where the next head starts, so such a
//! request is answered with `Connection: close` (see `http::manners`) and the rest of the
//! connection is passed through unchecked.

mod admission;
mod conn;
mod gate;
mod head;
mod rlimit;

pub use admission::{Connections, Refused, Registered};
pub use conn::{service, Conn, Deadlines, Ended, ResponseBody};
pub use gate::HeadGate;
pub use head::{HeadError, MAX_HEADERS, MAX_HEAD_BYTES, MAX_REQUEST_LINE_BYTES};
pub use rlimit::{cap_for, raise_descriptor_limit};
