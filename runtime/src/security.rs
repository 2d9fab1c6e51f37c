//! Transport security of every lcrl server and client: TLS (rustls, through
//! tonic), mutual TLS, and bearer tokens. Servers check the token in an
//! interceptor on every service but the health service and count refusals
//! by reason; clients attach it to every call. Plain text stays the default
//! on loopback.

use std::fmt;
use std::net::SocketAddr;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Arc;

use subtle::ConstantTimeEq;
use tokio_rustls::rustls;
use tonic::metadata::MetadataValue;
use tonic::service::Interceptor;
use tonic::transport::{Certificate, ClientTlsConfig, Endpoint, Identity};
use tonic::{Request, Status};

/// The environment variable naming the token file where no --token-file is given.
pub const TOKEN_FILE_ENV: &str = "LCRL_TOKEN_FILE";

#[derive(Debug, thiserror::Error)]
pub enum SecurityError {
    #[error("cannot read {what} {path}: {source}")]
    Read { what: &'static str, path: PathBuf, source: std::io::Error },
    #[error("{0}")]
    Invalid(String),
    #[error("cannot connect to {0}")]
    Connect(String),
}

/// An error with its sources, as one line (a TLS handshake failure hides
/// its reason two levels down).
pub fn error_chain(e: &dyn std::error::Error) -> String {
    let mut text = e.to_string();
    let mut source = e.source();
    while let Some(s) = source {
        text.push_str(&format!(": {s}"));
        source = s.source();
    }
    text
}

/// A shared secret. Its Debug and Display never show it.
#[derive(Clone)]
pub struct Token(Arc<str>);

impl fmt::Debug for Token {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str("Token(<redacted>)")
    }
}

impl Token {
    /// Reads a token file (surrounding whitespace ignored); or, with no
    /// path, the file $LCRL_TOKEN_FILE names; or none.
    pub fn load(path: Option<&Path>) -> Result<Option<Token>, SecurityError> {
        let from_env = std::env::var_os(TOKEN_FILE_ENV).map(PathBuf::from);
        let Some(path) = path.map(Path::to_path_buf).or(from_env) else { return Ok(None) };
        let text = std::fs::read_to_string(&path).map_err(|source| SecurityError::Read { what: "token file", path: path.clone(), source })?;
        let token = text.trim();
        if token.len() < 16 || !token.bytes().all(|b| b.is_ascii_graphic()) {
            return Err(SecurityError::Invalid(format!(
                "token file {} must hold one token of at least 16 printable characters (e.g. `lcrl certs` writes one)",
                path.display()
            )));
        }
        Ok(Some(Token(token.into())))
    }

    /// Constant-time comparison with a presented token.
    fn matches(&self, presented: &[u8]) -> bool {
        bool::from(self.0.as_bytes().ct_eq(presented))
    }

    fn header(&self) -> Result<MetadataValue<tonic::metadata::Ascii>, SecurityError> {
        format!("Bearer {}", self.0).parse().map_err(|_| SecurityError::Invalid("the token is not valid in a header".into()))
    }
}

/// Refused calls by reason, for GetStatus and /metrics.
#[derive(Debug, Default)]
pub struct AuthRefusals {
    /// No authorization header.
    pub missing: AtomicU64,
    /// A header that is not `Bearer <token>`.
    pub malformed: AtomicU64,
    /// A bearer token that does not match.
    pub wrong: AtomicU64,
    /// A TLS handshake that failed: plain text to a TLS port, no client
    /// certificate or one of another CA (mutual TLS), a timeout.
    pub tls_handshake: AtomicU64,
}

impl AuthRefusals {
    pub fn counts(&self) -> [(&'static str, u64); 4] {
        [
            ("missing_token", self.missing.load(Ordering::Relaxed)),
            ("malformed_token", self.malformed.load(Ordering::Relaxed)),
            ("wrong_token", self.wrong.load(Ordering::Relaxed)),
            ("tls_handshake", self.tls_handshake.load(Ordering::Relaxed)),
        ]
    }
}

/// The server-side token check, one per server, cloned into each service.
#[derive(Clone)]
pub struct TokenCheck {
    token: Option<Token>,
    refusals: Arc<AuthRefusals>,
    /// The server's connections: a call that passes marks its own
    /// (crate::incoming: one that never completes such a call is closed).
    connections: crate::incoming::Connections,
}

impl Interceptor for TokenCheck {
    fn call(&mut self, request: Request<()>) -> Result<Request<()>, Status> {
        let passed = self.check(&request);
        if let (Ok(()), Some(peer)) = (&passed, request.remote_addr()) {
            self.connections.mark_called(peer);
        }
        passed.map(|()| request)
    }
}

impl TokenCheck {
    fn check(&self, request: &Request<()>) -> Result<(), Status> {
        let Some(token) = &self.token else { return Ok(()) };
        let refuse = |counter: &AtomicU64, why: &str| {
            counter.fetch_add(1, Ordering::Relaxed);
            Err(Status::unauthenticated(why.to_string()))
        };
        match request.metadata().get("authorization") {
            None => refuse(&self.refusals.missing, "this server needs `authorization: Bearer <token>` (clients: --token-file)"),
            Some(value) => match value.as_bytes().strip_prefix(b"Bearer ") {
                None => refuse(&self.refusals.malformed, "the authorization header must be `Bearer <token>`"),
                Some(presented) if token.matches(presented) => Ok(()),
                Some(_) => refuse(&self.refusals.wrong, "the bearer token is not this server's"),
            },
        }
    }
}

/// Server flags, shared by lcrl-learner and lcrl-graph-builder.
#[derive(Debug, Clone, Default, clap::Args)]
pub struct ServerSecurityArgs {
    /// Serve TLS with this certificate (PEM; `lcrl certs` makes one).
    #[arg(long, value_name = "PEM", requires = "tls_key")]
    pub tls_cert: Option<PathBuf>,
    /// The certificate's private key (PEM).
    #[arg(long, value_name = "PEM", requires = "tls_cert")]
    pub tls_key: Option<PathBuf>,
    /// Mutual TLS: accept only clients with a certificate signed by this CA.
    #[arg(long, value_name = "PEM", requires = "tls_cert")]
    pub tls_client_ca: Option<PathBuf>,
    /// Require `authorization: Bearer <token>` on every call but health
    /// checks [default: the file $LCRL_TOKEN_FILE names, if set].
    #[arg(long, value_name = "FILE")]
    pub token_file: Option<PathBuf>,
    /// Connections and idle peers (crate::limits).
    #[command(flatten)]
    pub limits: crate::limits::ServerLimitsArgs,
}

/// Client flags, shared by every lcrl client of a learner or graph builder.
#[derive(Debug, Clone, Default, clap::Args)]
pub struct ClientSecurityArgs {
    /// Trust this CA for the server's certificate (PEM); the URL must be https://.
    #[arg(long, value_name = "PEM")]
    pub tls_ca: Option<PathBuf>,
    /// Mutual TLS: this client's certificate (PEM).
    #[arg(long, value_name = "PEM", requires_all = ["tls_client_key", "tls_ca"])]
    pub tls_client_cert: Option<PathBuf>,
    /// The client certificate's private key (PEM).
    #[arg(long, value_name = "PEM", requires = "tls_client_cert")]
    pub tls_client_key: Option<PathBuf>,
    /// Send `authorization: Bearer <token>` from this file [default: the
    /// file $LCRL_TOKEN_FILE names, if set].
    #[arg(long, value_name = "FILE")]
    pub token_file: Option<PathBuf>,
}

fn read(what: &'static str, path: &Path) -> Result<Vec<u8>, SecurityError> {
    std::fs::read(path).map_err(|source| SecurityError::Read { what, path: path.into(), source })
}

/// A rustls server configuration: this certificate, and with `client_ca`
/// only clients holding a certificate of that CA (mutual TLS).
pub fn server_config(cert: &[u8], key: &[u8], client_ca: Option<&[u8]>) -> Result<Arc<rustls::ServerConfig>, SecurityError> {
    use rustls::pki_types::pem::PemObject;
    use rustls::pki_types::{CertificateDer, PrivateKeyDer};
    let invalid = |what: &str, e: &dyn std::fmt::Display| SecurityError::Invalid(format!("{what}: {e}"));
    let chain = CertificateDer::pem_slice_iter(cert).collect::<Result<Vec<_>, _>>().map_err(|e| invalid("--tls-cert is not a PEM certificate", &e))?;
    let key = PrivateKeyDer::from_pem_slice(key).map_err(|e| invalid("--tls-key is not a PEM private key", &e))?;
    let provider = Arc::new(rustls::crypto::ring::default_provider());
    let builder = rustls::ServerConfig::builder_with_provider(provider.clone())
        .with_safe_default_protocol_versions()
        .map_err(|e| invalid("TLS", &e))?;
    let builder = match client_ca {
        Some(ca) => {
            let mut roots = rustls::RootCertStore::empty();
            for cert in CertificateDer::pem_slice_iter(ca) {
                roots.add(cert.map_err(|e| invalid("--tls-client-ca is not a PEM certificate", &e))?).map_err(|e| invalid("--tls-client-ca", &e))?;
            }
            let verifier = rustls::server::WebPkiClientVerifier::builder_with_provider(Arc::new(roots), provider)
                .build()
                .map_err(|e| invalid("--tls-client-ca", &e))?;
            builder.with_client_cert_verifier(verifier)
        }
        None => builder.with_no_client_auth(),
    };
    let mut config = builder.with_single_cert(chain, key).map_err(|e| invalid("--tls-cert and --tls-key do not match", &e))?;
    config.alpn_protocols = vec![b"h2".to_vec()];
    Ok(Arc::new(config))
}

/// A server's TLS and token settings, checked on start.
#[derive(Clone)]
pub struct ServerSecurity {
    tls: Option<Arc<tokio_rustls::rustls::ServerConfig>>,
    /// Whether TLS asks clients for a certificate of a CA (mutual TLS).
    mutual: bool,
    check: TokenCheck,
    limits: crate::limits::ServerLimitsArgs,
    connection_refusals: Arc<crate::limits::ConnectionRefusals>,
}

impl ServerSecurity {
    /// The name of run `run_id`'s shared memory for this server's token.
    pub fn shm_key(&self, run_id: &str) -> String {
        shm_run_key(run_id, self.check.token.as_ref())
    }

    pub fn from_args(args: &ServerSecurityArgs) -> Result<Self, SecurityError> {
        let tls = match (&args.tls_cert, &args.tls_key) {
            (Some(cert), Some(key)) => {
                let ca = args.tls_client_ca.as_deref().map(|ca| read("client CA", ca)).transpose()?;
                Some(server_config(&read("certificate", cert)?, &read("private key", key)?, ca.as_deref())?)
            }
            _ => None,
        };
        let token = Token::load(args.token_file.as_deref())?;
        let mutual = tls.is_some() && args.tls_client_ca.is_some();
        Ok(ServerSecurity {
            tls,
            mutual,
            check: TokenCheck { token, refusals: Arc::default(), connections: Default::default() },
            limits: args.limits.clone(),
            connection_refusals: Arc::default(),
        })
    }

    /// The interceptor to put in front of every service but health.
    pub fn token_check(&self) -> TokenCheck {
        self.check.clone()
    }

    pub fn refusals(&self) -> Arc<AuthRefusals> {
        self.check.refusals.clone()
    }

    /// The connections `listener` accepts: TLS where configured (failed
    /// handshakes counted), for `serve_with_incoming`.
    pub fn incoming(&self, listener: tokio::net::TcpListener) -> tokio_stream::wrappers::ReceiverStream<std::io::Result<crate::incoming::Conn>> {
        let refusals = self.check.refusals.clone();
        if let Err(why) = crate::limits::reserve_files(self.limits.max_connections) {
            tracing::warn!("{why}");
        }
        let limits = crate::incoming::Limits::new(&self.limits, self.connection_refusals.clone());
        let connections = self.check.connections.clone();
        crate::incoming::incoming(listener, self.tls.clone(), Arc::new(move || {
            refusals.tls_handshake.fetch_add(1, Ordering::Relaxed);
        }), limits, connections)
    }

    /// A tonic server with this server's limits (streams per connection,
    /// HTTP/2 pings that keep live clients from looking idle).
    pub fn server_builder(&self) -> tonic::transport::Server {
        self.limits.server()
    }

    /// Connections refused or closed (over the limit, idle), for /metrics.
    pub fn connection_refusals(&self) -> Arc<crate::limits::ConnectionRefusals> {
        self.connection_refusals.clone()
    }

    pub fn describe(&self) -> String {
        let transport = match (&self.tls, self.mutual) {
            (Some(_), true) => "mutual TLS",
            (Some(_), false) => "TLS",
            (None, _) => "plain text",
        };
        format!("{transport}{}", if self.check.token.is_some() { " + token" } else { "" })
    }

    /// Whether the server knows who calls it: every call but health checks
    /// needs the bearer token, or TLS accepts only clients with a
    /// certificate of its CA (mutual TLS).
    pub fn authenticates_peers(&self) -> bool {
        self.check.token.is_some() || (self.tls.is_some() && self.mutual)
    }

    /// A server reachable from other hosts without TLS is worth a warning.
    pub fn warn_if_exposed(&self, addr: SocketAddr) {
        if self.tls.is_none() && !addr.ip().is_loopback() {
            tracing::warn!(%addr, "serving plain text on a non-loopback address: anyone who can reach it can read the traffic{}; pass --tls-cert/--tls-key (see `lcrl certs`)", if self.check.token.is_none() { " and call every RPC" } else { "" });
        }
    }
}

/// A client's TLS and token settings.
#[derive(Clone, Default)]
pub struct ClientSecurity {
    tls: Option<ClientTlsConfig>,
    token: Option<Token>,
}

/// The name a run's shared-memory services go by (lcrl_proto::shm): the
/// run id, and with a token the first 16 hex digits of a SHA-256 digest of
/// it, so that a process without the token can neither find nor feed a
/// token-protected run's shared memory (issue 82). Without a token, the
/// run id itself.
pub fn shm_run_key(run_id: &str, token: Option<&Token>) -> String {
    match token {
        None => run_id.to_string(),
        Some(token) => {
            let digest = ring::digest::digest(&ring::digest::SHA256, format!("lcrl shared memory\0{}", token.0).as_bytes());
            let hex: String = digest.as_ref()[..8].iter().map(|b| format!("{b:02x}")).collect();
            format!("{run_id}.{hex}")
        }
    }
}

impl ClientSecurity {
    /// The name of run `run_id`'s shared memory for this client's token.
    pub fn shm_key(&self, run_id: &str) -> String {
        shm_run_key(run_id, self.token.as_ref())
    }

    pub fn from_args(args: &ClientSecurityArgs) -> Result<Self, SecurityError> {
        let identity = args.tls_client_cert.as_deref().zip(args.tls_client_key.as_deref());
        Self::new(args.tls_ca.as_deref(), identity, args.token_file.as_deref())
    }

    /// TLS trusting `ca` (with a client identity for mutual TLS), and the
    /// token from `token_file` (or $LCRL_TOKEN_FILE).
    pub fn new(ca: Option<&Path>, identity: Option<(&Path, &Path)>, token_file: Option<&Path>) -> Result<Self, SecurityError> {
        let tls = match ca {
            Some(ca) => {
                let mut config = ClientTlsConfig::new().ca_certificate(Certificate::from_pem(read("CA certificate", ca)?));
                if let Some((cert, key)) = identity {
                    config = config.identity(Identity::from_pem(read("client certificate", cert)?, read("client key", key)?));
                }
                Some(config)
            }
            None => None,
        };
        Ok(ClientSecurity { tls, token: Token::load(token_file)? })
    }

    /// Connects to `url` (TLS where configured); every call through the
    /// returned channel carries the token.
    pub async fn connect(&self, url: &str) -> Result<AuthChannel, SecurityError> {
        // The HTTP/2 handshake too has a deadline: a server that accepts
        // and never answers fails the connect instead of hanging it.
        let endpoint = self.endpoint(url)?;
        let channel = tokio::time::timeout(crate::limits::CALL_TIMEOUT, endpoint.connect())
            .await
            .map_err(|_| SecurityError::Connect(format!("{url}: did not answer within {} s", crate::limits::CALL_TIMEOUT.as_secs())))?
            .map_err(|e| SecurityError::Connect(format!("{url}: {}", error_chain(&e))))?;
        Ok(AuthChannel::new(channel, self.bearer()?))
    }

    /// An endpoint for `url` with TLS where configured: https:// needs
    /// --tls-ca, and --tls-ca needs https://.
    pub fn endpoint(&self, url: &str) -> Result<Endpoint, SecurityError> {
        let endpoint = Endpoint::from_shared(url.to_string()).map_err(|e| SecurityError::Invalid(format!("{url} is not a valid URL: {e}")))?;
        // Deadlines and pings: a client never hangs on a silent server.
        let endpoint = crate::limits::client_endpoint(endpoint);
        match (&self.tls, url.starts_with("https://")) {
            (Some(tls), true) => endpoint.tls_config(tls.clone()).map_err(|e| SecurityError::Invalid(format!("TLS for {url}: {e}"))),
            (None, false) => Ok(endpoint),
            (Some(_), false) => Err(SecurityError::Invalid(format!("--tls-ca is given but {url} is not https://; use https://HOST:PORT"))),
            (None, true) => Err(SecurityError::Invalid(format!("{url} is https:// but no --tls-ca says which CA to trust"))),
        }
    }

    /// The interceptor that attaches the token to every call.
    pub fn bearer(&self) -> Result<Bearer, SecurityError> {
        Ok(Bearer(self.token.as_ref().map(Token::header).transpose()?))
    }
}

/// Client side: adds `authorization: Bearer <token>` when there is a token.
#[derive(Clone)]
pub struct Bearer(Option<MetadataValue<tonic::metadata::Ascii>>);

impl Interceptor for Bearer {
    fn call(&mut self, mut request: Request<()>) -> Result<Request<()>, Status> {
        if let Some(value) = &self.0 {
            request.metadata_mut().insert("authorization", value.clone());
        }
        Ok(request)
    }
}

/// A channel whose every call carries the client's token.
pub type AuthChannel = tonic::service::interceptor::InterceptedService<tonic::transport::Channel, Bearer>;

#[cfg(test)]
mod tests {
    use super::*;

    fn token_file(text: &str) -> tempfile::NamedTempFile {
        let file = tempfile::NamedTempFile::new().unwrap();
        std::fs::write(file.path(), text).unwrap();
        file
    }

    fn check_with(token: &str) -> TokenCheck {
        let file = token_file(token);
        TokenCheck { token: Token::load(Some(file.path())).unwrap(), refusals: Arc::default(), connections: Default::default() }
    }

    fn call(check: &mut TokenCheck, header: Option<&str>) -> Result<(), tonic::Code> {
        let mut request = Request::new(());
        if let Some(h) = header {
            request.metadata_mut().insert("authorization", h.parse().unwrap());
        }
        check.call(request).map(|_| ()).map_err(|s| s.code())
    }

    #[test]
    fn tokens_are_checked_and_refusals_counted_by_reason() {
        let mut check = check_with("  s3cret-token-0123456789\n");
        assert_eq!(call(&mut check, Some("Bearer s3cret-token-0123456789")), Ok(()));
        assert_eq!(call(&mut check, None), Err(tonic::Code::Unauthenticated));
        assert_eq!(call(&mut check, Some("Basic s3cret-token-0123456789")), Err(tonic::Code::Unauthenticated));
        assert_eq!(call(&mut check, Some("Bearer s3cret-token-012345678")), Err(tonic::Code::Unauthenticated));
        assert_eq!(call(&mut check, Some("Bearer s3cret-token-01234567890")), Err(tonic::Code::Unauthenticated));
        let counts: Vec<u64> = check.refusals.counts().iter().map(|(_, n)| *n).collect();
        assert_eq!(counts, [1, 1, 2, 0], "missing, malformed, wrong, TLS handshake");
        // Without a token, everything passes.
        let mut open = TokenCheck { token: None, refusals: Arc::default(), connections: Default::default() };
        assert_eq!(call(&mut open, None), Ok(()));
    }

    #[test]
    fn tokens_never_print_and_weak_ones_are_refused() {
        let file = token_file("s3cret-token-0123456789");
        let token = Token::load(Some(file.path())).unwrap().unwrap();
        assert!(!format!("{token:?}").contains("s3cret"));
        let weak = token_file("short");
        let err = Token::load(Some(weak.path())).unwrap_err().to_string();
        assert!(err.contains("at least 16") && !err.contains("short"), "{err}");
        assert!(Token::load(Some(Path::new("/no/such/token"))).unwrap_err().to_string().contains("/no/such/token"));
    }

    #[test]
    fn scheme_and_tls_settings_must_agree() {
        let plain = ClientSecurity::default();
        assert!(plain.endpoint("http://127.0.0.1:1").is_ok());
        assert!(plain.endpoint("https://127.0.0.1:1").unwrap_err().to_string().contains("--tls-ca"));
    }
}
