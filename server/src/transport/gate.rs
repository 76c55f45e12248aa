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
                    if this.buf.is_empty() && !ready!(this.fill(cx))? {
                        return Poll::Ready(Ok(()));
                    }
                    let n = this.hand_over(out, left.min(usize::MAX as u64) as usize) as u64;
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
