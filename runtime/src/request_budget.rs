//! The memory all requests may hold while their messages arrive. A gRPC
//! message is buffered whole before it is decoded, so a peer that starts
//! messages of up to `--max-batch-bytes` on every stream of every
//! connection and never finishes them once held 32 × 512 × 1 MiB = 16 GiB
//! (issue 71), and a token-less `lcrl serve-env` 2 GiB (issue 82). Every
//! request body of every server's services (the learner, the graph builder,
//! `lcrl serve-env`; health and reflection included) takes from its
//! server's one budget, `--request-budget-mib`, the size of the largest message it
//! has declared (its 5-byte prefix: a compression flag and a big-endian u32
//! length), from the moment the prefix arrives until the stream ends:
//! tonic reserves a message's declared size when its prefix arrives, and a
//! stream's buffer keeps that capacity once the message is decoded. A
//! message that would go beyond the budget, or beyond its peer's quarter of
//! it, ends its stream with RESOURCE_EXHAUSTED ([`BUDGET_SPENT`]); an actor
//! resends it later. The prefixes are read as the body's chunks pass,
//! without copying them.

use std::net::IpAddr;
use std::pin::Pin;
use std::task::{Context, Poll};

use http_body::{Frame, SizeHint};
use tonic::body::Body;
use tonic::codegen::{http, Bytes, Service};
use tonic::server::NamedService;
use tonic::transport::server::TcpConnectInfo;
use tonic::Status;

use crate::memory_budget::{Held, MemoryBudget, Refusal};

/// The start of the refusal's message, so a server counts it apart from
/// a batch that is too large on its own.
pub const BUDGET_SPENT: &str = "request memory in use";

/// `--request-budget-mib` of the servers whose requests are small (the
/// graph builder, `lcrl serve-env`); the learner has its own, checked
/// against its largest batch.
#[derive(Debug, Clone, clap::Args)]
pub struct RequestBudgetArgs {
    /// MiB that all request streams together may hold while their messages
    /// arrive (health and reflection included); one peer address beyond
    /// loopback holds at most a quarter. A stream beyond it is refused with
    /// RESOURCE_EXHAUSTED.
    #[arg(long, default_value_t = 64, value_parser = clap::value_parser!(u64).range(1..=1_048_576))]
    pub request_budget_mib: u64,
}

impl RequestBudgetArgs {
    pub fn budget(&self, server: &'static str) -> RequestBudget {
        RequestBudget::new(self.request_budget_mib << 20, server)
    }
}

/// The budget (`--request-budget-mib`) of one server, named in refusals.
#[derive(Debug, Clone)]
pub struct RequestBudget(MemoryBudget, &'static str);

impl RequestBudget {
    /// `server` names the process in refusals ("learner", "graph builder").
    pub fn new(bytes: u64, server: &'static str) -> Self {
        RequestBudget(MemoryBudget::new(bytes), server)
    }

    /// Bytes the live streams hold now.
    pub fn used(&self) -> usize {
        self.0.used()
    }

    fn refusal(&self, refusal: Refusal) -> Status {
        let mib = |bytes: usize| bytes as f64 / f64::from(1 << 20);
        Status::resource_exhausted(match refusal {
            Refusal::PeerShare(ip) => format!("{BUDGET_SPENT}: {ip} holds its quarter of the {}'s memory for arriving messages, {:.0} MiB (--request-budget-mib); retry later", self.1, mib(self.0.peer_share())),
            Refusal::Full => format!("{BUDGET_SPENT}: the {} holds {:.0} MiB of arriving messages at most (--request-budget-mib); retry later", self.1, mib(self.0.total())),
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
        self.inner.call(request.map(|body| Body::new(Counted::new(body, budget, peer))))
    }
}

/// A request body holding a share of the budget: the largest message its
/// stream has declared, until it ends.
struct Counted {
    inner: Body,
    budget: RequestBudget,
    peer: Option<IpAddr>,
    framing: Framing,
    held: Option<Held>,
}

impl Counted {
    fn new(inner: Body, budget: RequestBudget, peer: Option<IpAddr>) -> Self {
        Counted { inner, budget, peer, framing: Framing::default(), held: None }
    }

    fn held_bytes(&self) -> usize {
        self.held.as_ref().map_or(0, Held::bytes)
    }

    /// A chunk passed on: the share grows to the largest message declared
    /// so far (its prefix included), or the stream is refused.
    fn on_chunk(&mut self, chunk: &[u8]) -> Result<(), Status> {
        let need = self.framing.feed(chunk);
        if need > self.held_bytes() {
            let more = self.budget.0.take(need - self.held_bytes(), self.peer).map_err(|refusal| self.budget.refusal(refusal))?;
            match &mut self.held {
                Some(held) => held.merge(more),
                None => self.held = Some(more),
            }
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
        if let Some(Ok(Some(data))) = frame.as_ref().map(|f| f.as_ref().map(Frame::data_ref)) {
            if let Err(status) = this.on_chunk(data) {
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
    /// The largest message declared so far, its prefix included (a prefix
    /// still arriving counts its bytes so far).
    largest: usize,
}

impl Framing {
    /// Reads one chunk; returns the largest message declared so far.
    fn feed(&mut self, mut chunk: &[u8]) -> usize {
        while !chunk.is_empty() {
            let take = if self.prefix_seen < 5 {
                let take = (5 - self.prefix_seen).min(chunk.len());
                self.prefix[self.prefix_seen..self.prefix_seen + take].copy_from_slice(&chunk[..take]);
                self.prefix_seen += take;
                self.largest = self.largest.max(self.prefix_seen);
                if self.prefix_seen == 5 {
                    let [_, a, b, c, d] = self.prefix;
                    self.body_left = u32::from_be_bytes([a, b, c, d]) as usize;
                    self.largest = self.largest.max(5 + self.body_left);
                }
                take
            } else {
                let take = self.body_left.min(chunk.len());
                self.body_left -= take;
                take
            };
            chunk = &chunk[take..];
            if self.prefix_seen == 5 && self.body_left == 0 {
                self.prefix_seen = 0;
            }
        }
        self.largest
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
    /// two in one chunk) are read the same: the largest declared so far is
    /// known from its prefix on.
    #[test]
    fn framing_finds_every_prefix_wherever_chunks_are_cut() {
        let wire: Vec<u8> = [message(10), message(0), message(300), message(20)].concat();
        for cut in 0..wire.len() {
            let mut framing = Framing::default();
            let first = framing.feed(&wire[..cut]);
            let expected = if cut < 5 { cut } else if cut < 25 { 15 } else { 305 };
            assert_eq!(first, expected, "cut at {cut}");
            assert_eq!(framing.feed(&wire[cut..]), 305, "cut at {cut}");
            assert_eq!((framing.prefix_seen, framing.body_left), (0, 0), "cut at {cut}: every message complete");
        }
    }

    /// A stream holds the largest message it has declared from its prefix
    /// on (before the body arrives) until it ends; one beyond the budget is
    /// refused with RESOURCE_EXHAUSTED naming the flag.
    #[test]
    fn a_stream_holds_its_largest_declared_message_until_it_ends() {
        let budget = RequestBudget::new(1000, "learner");
        let mut a = Counted::new(Body::empty(), budget.clone(), None);
        let big = message(600);
        a.on_chunk(&big[..5]).unwrap();
        assert_eq!(budget.used(), 605, "the declared size, from the prefix on");
        a.on_chunk(&big[5..]).unwrap();
        a.on_chunk(&message(10)).unwrap();
        assert_eq!(budget.used(), 605, "a smaller message adds nothing; the stream keeps its largest");
        let mut b = Counted::new(Body::empty(), budget.clone(), None);
        let refused = b.on_chunk(&message(500)[..5]).unwrap_err();
        assert_eq!(refused.code(), tonic::Code::ResourceExhausted);
        assert!(refused.message().starts_with(BUDGET_SPENT) && refused.message().contains("--request-budget-mib"), "{}", refused.message());
        drop(b);
        drop(a);
        assert_eq!(budget.used(), 0, "ended streams give back all they held");
    }
}
