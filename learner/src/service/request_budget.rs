//! The memory all requests may hold while their messages arrive. A gRPC
//! message is buffered whole before it is decoded, so a peer that starts
//! messages of up to `--max-batch-bytes` on every stream of every
//! connection and never finishes them once held 32 × 512 × 1 MiB = 16 GiB
//! (issue 71). Every request body of the Learner and Policy services now
//! takes the bytes of its unfinished message from one budget,
//! `--request-budget-mib`, as they arrive, and gives them back when the
//! message is complete (it is decoded at once, and what it decodes to waits
//! in a bounded queue) or the stream ends. A message that would go beyond
//! the budget, or beyond its peer's quarter of it, ends its stream with
//! RESOURCE_EXHAUSTED ([`BUDGET_SPENT`]); an actor resends it later.
//!
//! A message's bytes are known from gRPC's framing (a 5-byte prefix: a
//! compression flag and a big-endian u32 length), read here as the body's
//! chunks pass, without copying them.

use std::net::IpAddr;
use std::pin::Pin;
use std::task::{Context, Poll};

use http_body::{Frame, SizeHint};
use tonic::body::Body;
use tonic::codegen::{http, Bytes, Service};
use tonic::server::NamedService;
use tonic::transport::server::TcpConnectInfo;
use tonic::Status;

use crate::service::memory_budget::{Held, MemoryBudget, Refusal};

/// The start of the refusal's message, so the learner counts it apart from
/// a batch that is too large on its own.
pub const BUDGET_SPENT: &str = "request memory in use";

/// The budget (`--request-budget-mib`).
#[derive(Debug, Clone)]
pub struct RequestBudget(MemoryBudget);

impl RequestBudget {
    pub fn new(bytes: u64) -> Self {
        RequestBudget(MemoryBudget::new(bytes))
    }

    /// Bytes of unfinished messages held now.
    pub fn used(&self) -> usize {
        self.0.used()
    }

    fn refusal(&self, refusal: Refusal) -> Status {
        let mib = |bytes: usize| bytes as f64 / f64::from(1 << 20);
        Status::resource_exhausted(match refusal {
            Refusal::PeerShare(ip) => format!("{BUDGET_SPENT}: {ip} holds its quarter of the learner's memory for arriving messages, {:.0} MiB (--request-budget-mib); retry later", mib(self.0.peer_share())),
            Refusal::Full => format!("{BUDGET_SPENT}: the learner holds {:.0} MiB of arriving messages at most (--request-budget-mib); retry later", mib(self.0.total())),
        })
    }
}

/// A gRPC service whose request bodies count against a [`RequestBudget`].
#[derive(Debug, Clone)]
pub struct Budgeted<S> {
    inner: S,
    budget: RequestBudget,
}

impl<S> Budgeted<S> {
    pub fn new(inner: S, budget: RequestBudget) -> Self {
        Budgeted { inner, budget }
    }
}

impl<S: NamedService> NamedService for Budgeted<S> {
    const NAME: &'static str = S::NAME;
}

impl<S> Service<http::Request<Body>> for Budgeted<S>
where
    S: Service<http::Request<Body>>,
{
    type Response = S::Response;
    type Error = S::Error;
    type Future = S::Future;

    fn poll_ready(&mut self, cx: &mut Context<'_>) -> Poll<Result<(), Self::Error>> {
        self.inner.poll_ready(cx)
    }

    fn call(&mut self, request: http::Request<Body>) -> Self::Future {
        let peer = request.extensions().get::<TcpConnectInfo>().and_then(TcpConnectInfo::remote_addr).map(|addr| addr.ip());
        let budget = self.budget.clone();
        self.inner.call(request.map(|body| Body::new(Counted { inner: body, budget, peer, framing: Framing::default(), held: Vec::new(), held_bytes: 0 })))
    }
}

/// A request body holding a share of the budget for its unfinished message.
struct Counted {
    inner: Body,
    budget: RequestBudget,
    peer: Option<IpAddr>,
    framing: Framing,
    /// The unfinished message's shares, one per chunk that added to it.
    held: Vec<Held>,
    held_bytes: usize,
}

impl Counted {
    /// Holds exactly the unfinished message's `partial` bytes.
    fn hold(&mut self, partial: usize) -> Result<(), Status> {
        if partial < self.held_bytes {
            // A message was completed (and perhaps the next begun).
            self.held.clear();
            self.held_bytes = 0;
        }
        if partial > self.held_bytes {
            let share = self.budget.0.take(partial - self.held_bytes, self.peer).map_err(|refusal| self.budget.refusal(refusal))?;
            self.held.push(share);
            self.held_bytes = partial;
        }
        Ok(())
    }
}

impl http_body::Body for Counted {
    type Data = Bytes;
    type Error = Status;

    fn poll_frame(mut self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<Option<Result<Frame<Bytes>, Status>>> {
        let this = &mut *self;
        let frame = match Pin::new(&mut this.inner).poll_frame(cx) {
            Poll::Pending => return Poll::Pending,
            Poll::Ready(frame) => frame,
        };
        if let Some(Ok(data)) = frame.as_ref().map(|f| f.as_ref().map(Frame::data_ref)) {
            let partial = data.map_or(this.framing.partial, |bytes| this.framing.feed(bytes));
            if let Err(status) = this.hold(partial) {
                tracing::warn!(peer = ?this.peer, %status, "request refused");
                return Poll::Ready(Some(Err(status)));
            }
        }
        Poll::Ready(frame)
    }

    fn is_end_stream(&self) -> bool {
        self.inner.is_end_stream()
    }

    fn size_hint(&self) -> SizeHint {
        self.inner.size_hint()
    }
}

/// Where a body stands in gRPC's framing.
#[derive(Debug, Default)]
struct Framing {
    prefix: [u8; 5],
    prefix_seen: usize,
    /// Bytes of the message's body still to come, once its prefix is read.
    body_left: usize,
    /// Bytes of the unfinished message seen (its prefix included).
    partial: usize,
}

impl Framing {
    /// Reads one chunk; returns the bytes of the message still unfinished
    /// after it (0 at a message boundary).
    fn feed(&mut self, mut chunk: &[u8]) -> usize {
        while !chunk.is_empty() {
            let take = if self.prefix_seen < 5 {
                let take = (5 - self.prefix_seen).min(chunk.len());
                self.prefix[self.prefix_seen..self.prefix_seen + take].copy_from_slice(&chunk[..take]);
                self.prefix_seen += take;
                if self.prefix_seen == 5 {
                    let [_, a, b, c, d] = self.prefix;
                    self.body_left = u32::from_be_bytes([a, b, c, d]) as usize;
                }
                take
            } else {
                let take = self.body_left.min(chunk.len());
                self.body_left -= take;
                take
            };
            self.partial += take;
            chunk = &chunk[take..];
            if self.prefix_seen == 5 && self.body_left == 0 {
                (self.prefix_seen, self.partial) = (0, 0);
            }
        }
        self.partial
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn message(len: u32) -> Vec<u8> {
        let mut m = vec![0u8];
        m.extend_from_slice(&len.to_be_bytes());
        m.extend(std::iter::repeat_n(7u8, len as usize));
        m
    }

    /// Messages cut at every place (inside the prefix, inside the body,
    /// two in one chunk) leave exactly their unfinished bytes counted.
    #[test]
    fn framing_counts_the_unfinished_message_wherever_chunks_are_cut() {
        let wire: Vec<u8> = [message(10), message(0), message(300)].concat();
        for cut in 0..wire.len() {
            let mut framing = Framing::default();
            let first = framing.feed(&wire[..cut]);
            let expected = if cut < 15 { cut } else if cut < 20 { cut - 15 } else { cut - 20 };
            assert_eq!(first, expected, "cut at {cut}");
            assert_eq!(framing.feed(&wire[cut..]), 0, "cut at {cut}: all three messages complete");
        }
    }

    /// An unfinished message holds its bytes, a finished one gives them
    /// back, and one beyond the budget is refused with RESOURCE_EXHAUSTED
    /// naming the flag.
    #[test]
    fn unfinished_messages_hold_their_bytes_and_the_budget_refuses_beyond_it() {
        let budget = RequestBudget::new(1000);
        let body = |budget: &RequestBudget| Counted { inner: Body::empty(), budget: budget.clone(), peer: None, framing: Framing::default(), held: Vec::new(), held_bytes: 0 };
        let mut a = body(&budget);
        let big = message(900);
        let partial = a.framing.feed(&big[..600]);
        a.hold(partial).unwrap();
        assert_eq!(budget.used(), 600);
        let mut b = body(&budget);
        let partial = b.framing.feed(&big[..500]);
        let refused = b.hold(partial).unwrap_err();
        assert_eq!(refused.code(), tonic::Code::ResourceExhausted);
        assert!(refused.message().starts_with(BUDGET_SPENT) && refused.message().contains("--request-budget-mib"), "{}", refused.message());
        let partial = a.framing.feed(&big[600..]);
        a.hold(partial).unwrap();
        assert_eq!(budget.used(), 0, "a finished message gives its bytes back");
        b.hold(500).unwrap();
        drop(b);
        assert_eq!(budget.used(), 0, "an ended stream gives its bytes back");
    }
}
