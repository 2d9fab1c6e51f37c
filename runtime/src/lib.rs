//! What every lcrl service process needs at start-up and at run time,
//! beside the contract (lcrl-proto): [`process`], the start-up, logging,
//! shutdown and reflection every process shares; [`security`], how every
//! server and client authenticates (TLS, tokens); [`incoming`], the
//! TLS-accepting connection stream servers are fed from; [`limits`], the
//! bounds every server keeps against its peers and the deadlines every
//! client keeps; [`peer_rate`], calls a second per peer address;
//! [`peer_process`], which host or local process a peer is;
//! [`memory_budget`] and [`request_budget`], the bytes peers may make a
//! server hold and the request bodies that take from them; [`files`],
//! the one atomic writer of the files those processes hand on; and
//! [`metrics_http`], Prometheus `/metrics` and `/healthz` over HTTP.

pub mod files;
pub mod incoming;
pub mod limits;
pub mod memory_budget;
pub mod metrics_http;
pub mod peer_process;
pub mod peer_rate;
pub mod process;
pub mod request_budget;
pub mod security;
