//! What every lcrl service process shares, so the graph builder, the
//! learner and the actor start, log, stop and describe themselves alike:
//! [`run_service`] (the `main()` of each), [`init_logging`],
//! [`shutdown_signal`] and [`add_reflection`].

use std::future::Future;
use std::process::ExitCode;

use tonic::service::interceptor::InterceptedService;
use tonic_reflection::server as reflection;

use crate::security::TokenCheck;

/// The body of a service binary's `main()`: logging (JSON lines with
/// `log_json`), a multi-threaded async runtime with `workers` threads, and
/// `run` on it; an error is printed as one `NAME: error: …` line (with its
/// causes) and exits non-zero.
pub fn run_service<F>(name: &str, log_json: bool, workers: usize, run: F) -> ExitCode
where
    F: Future<Output = anyhow::Result<()>>,
{
    init_logging(log_json);
    return_large_allocations();
    let runtime = match tokio::runtime::Builder::new_multi_thread().worker_threads(workers.max(1)).enable_all().build() {
        Ok(runtime) => runtime,
        Err(e) => {
            eprintln!("{name}: error: cannot start the async runtime: {e}");
            return ExitCode::FAILURE;
        }
    };
    match runtime.block_on(run) {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("{name}: error: {}", error_chain(&e));
            ExitCode::FAILURE
        }
    }
}

/// Large blocks (2 MiB and up: big policies and their encoded replies)
/// come straight from
/// the kernel and go back to it when freed. Otherwise glibc raises its
/// mmap threshold to the largest block freed so far, and blocks of that
/// size then live in its heaps, which it keeps: 8 rounds of 64 slow
/// WatchPolicy readers once left the learner at 705 MiB where it had
/// started at 160 (issue 71). A fixed threshold also stops the raising.
fn return_large_allocations() {
    #[cfg(all(target_os = "linux", target_env = "gnu"))]
    // SAFETY: mallopt only sets a number in glibc's allocator; it is
    // called before any thread of ours starts.
    unsafe {
        libc::mallopt(libc::M_MMAP_THRESHOLD, 2 << 20);
    }
}

/// An error and its causes on one line, `outer: cause: …`, as `{:#}`
/// prints them, but without repeating a cause whose text the message
/// before it already ends with (an I/O error whose message embeds its
/// `source`, e.g. `missing.toml: No such file or directory (os error 2)`,
/// would otherwise print its cause twice).
pub fn error_chain(e: &anyhow::Error) -> String {
    let mut chain = e.chain();
    let first = chain.next().map(ToString::to_string).unwrap_or_default();
    let mut line = with_causes(first, chain);
    let lower = line.to_lowercase();
    if ["broken pipe", "connection reset", "connection closed", "received fatal alert"].iter().any(|cut| lower.contains(cut)) {
        // Under TLS 1.3 a server that refuses the client's certificate does
        // so after the client's handshake ended: the client sees only the
        // closed connection (issue 71).
        line.push_str(
            " (the server closed the connection; under mutual TLS it does so when it refuses this client's certificate: \
             is --tls-client-cert signed by the CA the server trusts, its --tls-client-ca?)",
        );
    }
    line
}

/// `first: cause: …`, each cause's text once (one the line so far already ends
/// with is left out): the line of [`error_chain`], and of a failed call's
/// status with its transport causes.
pub fn with_causes<'a>(first: String, causes: impl Iterator<Item = &'a (dyn std::error::Error + 'static)>) -> String {
    let mut line = first;
    for cause in causes {
        let text = cause.to_string();
        if line.is_empty() {
            line = text;
        } else if !text.is_empty() && !line.ends_with(&text) {
            line.push_str(": ");
            line.push_str(&text);
        }
    }
    line
}

/// A clap value parser for a count from `LO` to `HI`: a value outside is
/// refused, with the range, as the arguments are parsed (a typo must not
/// become a huge allocation or an overflow later on).
pub fn count_in<const LO: usize, const HI: usize>(text: &str) -> Result<usize, String> {
    let value: usize = text.trim().parse().map_err(|_| format!("expected a whole number from {LO} to {HI}"))?;
    if (LO..=HI).contains(&value) {
        Ok(value)
    } else {
        Err(format!("{value} is out of range: expected {LO} to {HI}"))
    }
}

/// Resolves on SIGTERM or Ctrl-C: how every lcrl server and actor stops.
pub async fn shutdown_signal() {
    let ctrl_c = tokio::signal::ctrl_c();
    match tokio::signal::unix::signal(tokio::signal::unix::SignalKind::terminate()) {
        Ok(mut term) => {
            tokio::select! {
                _ = ctrl_c => {},
                _ = term.recv() => {},
            }
        }
        Err(_) => {
            let _ = ctrl_c.await;
        }
    }
}

/// Logging of every lcrl process: to stderr, human-readable by default or
/// JSON lines with `json`, level from `RUST_LOG` (default `info`).
pub fn init_logging(json: bool) {
    let filter = tracing_subscriber::EnvFilter::try_from_default_env().unwrap_or_else(|_| "info".into());
    let builder = tracing_subscriber::fmt()
        .with_env_filter(filter)
        .with_writer(std::io::stderr)
        .with_ansi(!json && std::io::IsTerminal::is_terminal(&std::io::stderr()));
    if json {
        builder.json().init();
    } else {
        builder.init();
    }
}

/// The decoding limit of services whose requests are a name or nothing
/// (health, reflection, the graph): a peer cannot make them buffer more.
pub const SMALL_REQUEST_BYTES: usize = 64 << 10;

/// The standard health service (no token needed) with
/// [`SMALL_REQUEST_BYTES`] as its decoding limit.
pub fn health_service() -> (tonic_health::server::HealthReporter, tonic_health::pb::health_server::HealthServer<impl tonic_health::pb::health_server::Health>) {
    let (reporter, service) = tonic_health::server::health_reporter();
    (reporter, service.max_decoding_message_size(SMALL_REQUEST_BYTES))
}

/// Adds server reflection of lcrl.v1 and grpc.health.v1 in both protocol
/// versions, behind the token check: v1 (grpcurl, grpcui, newer tools) and
/// v1alpha (grpcio's `grpcio-reflection`, Postman, older tools).
pub fn add_reflection<L>(router: tonic::transport::server::Router<L>, check: &TokenCheck, budget: &crate::request_budget::RequestBudget) -> tonic::transport::server::Router<L> {
    let configure = || {
        reflection::Builder::configure()
            .register_encoded_file_descriptor_set(lcrl_proto::v1::FILE_DESCRIPTOR_SET)
            .register_encoded_file_descriptor_set(tonic_health::pb::FILE_DESCRIPTOR_SET)
    };
    // The descriptor sets are compiled in: a failure is a build defect,
    // which every test that starts a server would show.
    // Its requests name a symbol or a file: nothing larger is decoded.
    let v1 = configure().build_v1().expect("compiled-in descriptor sets are valid").max_decoding_message_size(SMALL_REQUEST_BYTES);
    let v1alpha = configure().build_v1alpha().expect("compiled-in descriptor sets are valid").max_decoding_message_size(SMALL_REQUEST_BYTES);
    // Its streams take from the server's request budget, as every
    // service's do (a flood of unfinished reflection streams once kept
    // 661 MiB, issue 82).
    use crate::request_budget::Budgeted;
    router
        .add_service(InterceptedService::new(Budgeted::new(v1, budget.clone()), check.clone()))
        .add_service(InterceptedService::new(Budgeted::new(v1alpha, budget.clone()), check.clone()))
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A closed connection names the TLS refusal it may be; other errors
    /// read as they are.
    #[test]
    fn a_closed_connection_names_the_tls_refusal() {
        let closed = anyhow::Error::new(std::io::Error::from(std::io::ErrorKind::BrokenPipe)).context("GetStatus");
        let line = error_chain(&closed);
        assert!(line.starts_with("GetStatus: broken pipe") && line.contains("--tls-client-ca"), "{line}");
        let other = anyhow::anyhow!("no such file");
        assert_eq!(error_chain(&other), "no such file");
    }

    /// An I/O error whose message embeds its source (thiserror's
    /// `#[error("{path}: {source}")]`) is printed once, not twice; other
    /// causes still follow with ": ".
    #[test]
    fn an_error_chain_does_not_repeat_its_cause() {
        #[derive(Debug)]
        struct Io(std::io::Error);
        impl std::fmt::Display for Io {
            fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
                write!(f, "missing.toml: {}", self.0)
            }
        }
        impl std::error::Error for Io {
            fn source(&self) -> Option<&(dyn std::error::Error + 'static)> {
                Some(&self.0)
            }
        }
        let cause = std::io::Error::new(std::io::ErrorKind::NotFound, "No such file or directory");
        let e = anyhow::Error::new(Io(cause)).context("reading the config");
        assert_eq!(error_chain(&e), "reading the config: missing.toml: No such file or directory");
        let e = anyhow::anyhow!("inner").context("outer");
        assert_eq!(error_chain(&e), "outer: inner");
    }

    #[test]
    fn counts_are_checked_against_their_range() {
        assert_eq!(count_in::<1, 10>("10"), Ok(10));
        for bad in ["0", "11", "-1", "x", "18446744073709551616"] {
            let err = count_in::<1, 10>(bad).unwrap_err();
            assert!(err.contains("1 to 10"), "{bad}: {err}");
        }
    }
}
