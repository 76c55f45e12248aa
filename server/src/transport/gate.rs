//! The gate between the socket and hyper, which reads and checks every request head first.

use std::future::Future;
use std::io;
use std::pin::Pin;
use std::sync::atomic::Ordering;
use std::sync::Arc;
use std::task::{ready, Context, Poll};
use std::time::Duration;

use tokio::io::{AsyncRead, AsyncWrite, ReadBuf};
use tokio::time::{Instant, Sleep};

use super::conn::{Conn, Deadlines};
use super::head::{check_head, Framing, HeadError, STAND_IN};

#[derive(Debug)]
enum Mode {
    /// Reading a head; `started` once its first byte arrived (or from accept).
    Head { started: bool },
    /// Handing hyper `left` bytes of an accepted head, then the body.
    Release { left: usize, then: Framing },
    /// Handing hyper `left` bytes of body.
    Body { left: u64 },
    /// Everything as it comes.
    Passthrough,
    /// Handing hyper the stand-in head of a refused one, then nothing.
    StandIn { at: usize },
    /// Nothing more, ever: hyper answers the stand-in and closes the connection (an end of
    /// stream instead would make hyper drop the connection before it answers).
    Hold,
    /// End of stream.
    Closed,
}

/// The socket as hyper sees it: request heads are read and checked here first (see the module
/// docs). Writes pass straight through.
pub struct HeadGate<T> {
    io: T,
    conn: Arc<Conn>,
    deadlines: Deadlines,
    /// Bytes read from the socket, not yet handed to hyper.
    buf: Vec<u8>,
    mode: Mode,
    timer: Pin<Box<Sleep>>,
}

impl<T> HeadGate<T> {
    /// A gate on a freshly accepted socket: its first head is due within the head deadline.
    pub fn new(io: T, conn: Arc<Conn>, deadlines: Deadlines) -> HeadGate<T> {
        HeadGate {
            io,
            conn,
            deadlines,
            buf: Vec::new(),
            mode: Mode::Head { started: true },
            timer: Box::pin(tokio::time::sleep(deadlines.head)),
        }
    }

    fn arm(&mut self, after: Duration) {
        self.timer.as_mut().reset(Instant::now() + after);
    }

    fn refuse(&mut self, refusal: HeadError) {
        tracing::debug!(error = %refusal, "request head refused");
        *self.conn.refusal.lock().unwrap_or_else(|e| e.into_inner()) = Some(refusal);
        self.buf.clear();
        self.mode = Mode::StandIn { at: 0 };
    }

    /// Hands hyper up to `n` buffered bytes.
    fn hand_over(&mut self, out: &mut ReadBuf<'_>, n: usize) -> usize {
        let n = n.min(self.buf.len()).min(out.remaining());
        out.put_slice(&self.buf[..n]);
        self.buf.drain(..n);
        n
    }
}

impl<T: AsyncRead + Unpin> HeadGate<T> {
    /// Reads at most `limit` bytes of the socket straight into `out`, returning how many (0 at
    /// end of stream, or if `out` is full).
    fn read_into(
        &mut self,
        cx: &mut Context<'_>,
        out: &mut ReadBuf<'_>,
        limit: usize,
    ) -> Poll<io::Result<usize>> {
        let mut part = out.take(limit);
        let start = part.filled().as_ptr();
        ready!(Pin::new(&mut self.io).poll_read(cx, &mut part))?;
        assert_eq!(
            part.filled().as_ptr(),
            start,
            "the reader kept to its buffer"
        );
        let n = part.filled().len();
        // SAFETY: `part` is `out`'s unfilled memory, and the reader filled its first `n`
        // bytes (a `ReadBuf`'s filled bytes are initialized).
        unsafe { out.assume_init(n) };
        out.advance(n);
        Poll::Ready(Ok(n))
    }

    /// Reads more of the socket into the buffer: `Ok(false)` at end of stream.
    fn fill(&mut self, cx: &mut Context<'_>) -> Poll<io::Result<bool>> {
        let mut chunk = [0u8; 16 * 1024];
        let mut read = ReadBuf::new(&mut chunk);
        ready!(Pin::new(&mut self.io).poll_read(cx, &mut read))?;
        self.buf.extend_from_slice(read.filled());
        Poll::Ready(Ok(!read.filled().is_empty()))
    }
}

impl<T: AsyncRead + Unpin> AsyncRead for HeadGate<T> {
    fn poll_read(
        self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        out: &mut ReadBuf<'_>,
    ) -> Poll<io::Result<()>> {
        let this = self.get_mut();
        loop {
            match this.mode {
                Mode::Closed => return Poll::Ready(Ok(())),
                Mode::Hold => return Poll::Pending,
                Mode::StandIn { at } => {
                    let n = (STAND_IN.len() - at).min(out.remaining());
                    out.put_slice(&STAND_IN[at..at + n]);
                    this.mode = if at + n == STAND_IN.len() {
                        Mode::Hold
                    } else {
                        Mode::StandIn { at: at + n }
                    };
                    return Poll::Ready(Ok(()));
                }
                Mode::Release { left, then } => {
                    let n = this.hand_over(out, left);
                    if n == left {
                        this.mode = match then {
                            Framing::Length(0) => {
                                this.arm(this.deadlines.idle);
                                Mode::Head { started: false }
                            }
                            Framing::Length(n) => Mode::Body { left: n },
                            Framing::Chunked => Mode::Passthrough,
                        };
                    } else {
                        this.mode = Mode::Release {
                            left: left - n,
                            then,
                        };
                    }
                    return Poll::Ready(Ok(()));
                }
                Mode::Body { left } => {
                    let limit = left.min(usize::MAX as u64) as usize;
                    let n = if this.buf.is_empty() {
                        // Straight from the socket into hyper's buffer, never past this body:
                        // a large body (a state, a pass) is not copied here on its way.
                        let n = ready!(this.read_into(cx, out, limit))?;
                        if n == 0 {
                            return Poll::Ready(Ok(()));
                        }
                        n as u64
                    } else {
                        this.hand_over(out, limit) as u64
                    };
                    this.mode = if n == left {
                        this.arm(this.deadlines.idle);
                        Mode::Head { started: false }
                    } else {
                        Mode::Body { left: left - n }
                    };
                    return Poll::Ready(Ok(()));
                }
                Mode::Passthrough => {
                    if !this.buf.is_empty() {
                        this.hand_over(out, usize::MAX);
                        return Poll::Ready(Ok(()));
                    }
                    return Pin::new(&mut this.io).poll_read(cx, out);
                }
                Mode::Head { started } => {
                    if !this.buf.is_empty() {
                        if !started {
                            this.arm(this.deadlines.head);
                            this.mode = Mode::Head { started: true };
                        }
                        match check_head(&this.buf) {
                            Ok(Some((len, framing))) => {
                                this.conn.had_head.store(true, Ordering::Release);
                                this.mode = Mode::Release {
                                    left: len,
                                    then: framing,
                                };
                                continue;
                            }
                            Ok(None) => {}
                            Err(refusal) => {
                                this.refuse(refusal);
                                continue;
                            }
                        }
                    }
                    match this.fill(cx) {
                        Poll::Ready(Ok(true)) => continue,
                        // The client went away (between requests, or mid-head).
                        Poll::Ready(Ok(false)) => {
                            this.mode = Mode::Closed;
                            continue;
                        }
                        Poll::Ready(Err(e)) => return Poll::Ready(Err(e)),
                        Poll::Pending => {
                            ready!(this.timer.as_mut().poll(cx));
                            tracing::debug!(
                                started,
                                "no complete request head in time: closing the connection"
                            );
                            metrics::counter!(
                                crate::meters::CONNECTIONS_CLOSED,
                                "reason" => if started { "head_timeout" } else { "idle" }
                            )
                            .increment(1);
                            this.mode = Mode::Closed;
                            continue;
                        }
                    }
                }
            }
        }
    }
}

impl<T: AsyncWrite + Unpin> AsyncWrite for HeadGate<T> {
    fn poll_write(
        self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        data: &[u8],
    ) -> Poll<io::Result<usize>> {
        Pin::new(&mut self.get_mut().io).poll_write(cx, data)
    }

    fn poll_write_vectored(
        self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        bufs: &[io::IoSlice<'_>],
    ) -> Poll<io::Result<usize>> {
        Pin::new(&mut self.get_mut().io).poll_write_vectored(cx, bufs)
    }

    fn is_write_vectored(&self) -> bool {
        self.io.is_write_vectored()
    }

    /// Hyper flushes after writing, its own buffer first: once this is ready, every byte of a
    /// response whose body has ended is in the socket, and its request is over.
    fn poll_flush(self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<io::Result<()>> {
        let this = self.get_mut();
        ready!(Pin::new(&mut this.io).poll_flush(cx))?;
        drop(this.conn.finish());
        Poll::Ready(Ok(()))
    }

    fn poll_shutdown(self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<io::Result<()>> {
        Pin::new(&mut self.get_mut().io).poll_shutdown(cx)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::transport::Connections;

    /// A socket that hands out `bytes` in pieces of varying size, as a network does.
    struct Trickle {
        bytes: Vec<u8>,
        at: usize,
        piece: usize,
    }

    impl AsyncRead for Trickle {
        fn poll_read(
            self: Pin<&mut Self>,
            _: &mut Context<'_>,
            out: &mut ReadBuf<'_>,
        ) -> Poll<io::Result<()>> {
            let this = self.get_mut();
            this.piece = this.piece * 7 % 9973 + 1;
            let n = this
                .piece
                .min(out.remaining())
                .min(this.bytes.len() - this.at);
            out.put_slice(&this.bytes[this.at..this.at + n]);
            this.at += n;
            Poll::Ready(Ok(()))
        }
    }

    /// What hyper is handed through the gate, read into buffers of `room` bytes, until the gate
    /// holds (a refused head) or the stream ends.
    fn through_gate(bytes: Vec<u8>, room: usize) -> Vec<u8> {
        let connections = Arc::new(Connections::new(4));
        let registered = connections.admit().expect("room for one");
        let long = Duration::from_secs(3600);
        let deadlines = Deadlines {
            head: long,
            idle: long,
            response: long,
        };
        let socket = Trickle {
            bytes,
            at: 0,
            piece: 1,
        };
        let mut gate = HeadGate::new(socket, registered.conn().clone(), deadlines);
        let mut cx = Context::from_waker(std::task::Waker::noop());
        let mut seen = Vec::new();
        let mut buf = vec![0u8; room];
        loop {
            let mut out = ReadBuf::new(&mut buf);
            match Pin::new(&mut gate).poll_read(&mut cx, &mut out) {
                Poll::Ready(Ok(())) if out.filled().is_empty() => return seen,
                Poll::Ready(Ok(())) => seen.extend_from_slice(out.filled()),
                Poll::Ready(Err(e)) => panic!("{e}"),
                Poll::Pending => return seen,
            }
        }
    }

    /// A body is handed over byte for byte (straight from the socket where nothing of it was
    /// buffered with its head), and never a byte past it: the next head is checked, so one
    /// that breaks the rules is answered by the stand-in, whatever the pieces and the room.
    #[tokio::test]
    async fn a_body_passes_whole_and_the_head_after_it_is_still_checked() {
        let body: Vec<u8> = (0..300_000u32).map(|i| (i * 31 % 251) as u8).collect();
        let first = format!(
            "POST /v1/frames/f/state HTTP/1.1\r\nhost: x\r\ncontent-length: {}\r\n\r\n",
            body.len()
        );
        let second = b"GET /v1/frames HTTP/1.1\r\nhost: x\r\n\r\n";
        let third = b"GET / HTTP/1.1\r\nbad header\r\n\r\n";
        let mut sent = first.into_bytes();
        sent.extend_from_slice(&body);
        sent.extend_from_slice(second);
        let mut expected = sent.clone();
        sent.extend_from_slice(third);
        sent.extend_from_slice(b"GET /smuggled HTTP/1.1\r\n\r\n");
        expected.extend_from_slice(STAND_IN);
        for room in [1, 7, 4096, 65_536, 1 << 20] {
            let seen = through_gate(sent.clone(), room);
            assert!(seen == expected, "room {room}: {} bytes", seen.len());
        }
    }
}
