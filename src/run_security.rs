//! How every process of a run is secured: TLS from a folder `lcrl certs`
//! wrote and a bearer token, as command-line flags for servers and
//! clients. `lcrl run` (one machine) and `lcrl launch` (containers, pods)
//! both use it, so a run is secured the same way everywhere.

use std::ffi::OsString;
use std::path::{Path, PathBuf};

use anyhow::{bail, Context};

/// TLS and the token for every process of a run: a folder `lcrl certs`
/// wrote and a token file. Shared by `lcrl run` (one machine) and
/// `lcrl launch` (containers, pods), so both secure a run the same way.
#[derive(Debug, Clone, Default, clap::Args)]
pub struct RunSecurity {
    /// TLS from a folder `lcrl certs` wrote (ca.pem, server.pem/.key,
    /// client.pem/.key): servers serve TLS and accept only clients with a
    /// certificate of that CA (mutual TLS), clients show theirs, and URLs
    /// use https://.
    #[arg(long, value_name = "DIR")]
    pub tls_dir: Option<PathBuf>,
    /// The bearer token: servers require it on every call but health
    /// checks, clients send it [default: the file $LCRL_TOKEN_FILE names].
    #[arg(long, value_name = "FILE")]
    pub token_file: Option<PathBuf>,
}

impl RunSecurity {
    /// A file of the TLS folder, checked to exist.
    fn file(dir: &Path, name: &str) -> anyhow::Result<OsString> {
        let path = dir.join(name);
        if !path.is_file() {
            bail!("{} is missing: --tls-dir must hold what `lcrl certs` writes (ca.pem, server.pem, server.key, client.pem, client.key)", path.display());
        }
        Ok(path.into_os_string())
    }

    /// `url` with https:// under TLS.
    pub fn url(&self, url: &str) -> String {
        match (&self.tls_dir, url.strip_prefix("http://")) {
            (Some(_), Some(rest)) => format!("https://{rest}"),
            _ => url.to_string(),
        }
    }

    fn token_args(&self) -> Vec<OsString> {
        self.token_file.iter().flat_map(|t| [OsString::from("--token-file"), t.clone().into_os_string()]).collect()
    }

    /// A server's flags (graph builder; learner, which with `graph_client`
    /// also trusts the CA for the graph builder).
    pub fn server_args(&self, graph_client: bool) -> anyhow::Result<Vec<OsString>> {
        let mut args = Vec::new();
        if let Some(dir) = &self.tls_dir {
            args.extend([OsString::from("--tls-cert"), Self::file(dir, "server.pem")?, "--tls-key".into(), Self::file(dir, "server.key")?]);
            args.extend([OsString::from("--tls-client-ca"), Self::file(dir, "ca.pem")?]);
            if graph_client {
                args.extend([OsString::from("--graph-builder-tls-ca"), Self::file(dir, "ca.pem")?]);
            }
        }
        args.extend(self.token_args());
        Ok(args)
    }

    /// An actor's flags.
    pub fn client_args(&self) -> anyhow::Result<Vec<OsString>> {
        let mut args = Vec::new();
        if let Some(dir) = &self.tls_dir {
            args.extend([OsString::from("--tls-ca"), Self::file(dir, "ca.pem")?, "--tls-client-cert".into(), Self::file(dir, "client.pem")?]);
            args.extend([OsString::from("--tls-client-key"), Self::file(dir, "client.key")?]);
        }
        args.extend(self.token_args());
        Ok(args)
    }

    /// Makes this process, and every process it starts afterwards, a client
    /// of a secured environment server (`lcrl_env serve`): the variables
    /// `lcrl_sim::remote` reads for `grpcs://` URLs, and $LCRL_TOKEN_FILE.
    /// Call it before any thread starts.
    pub fn export_env_client(&self) -> anyhow::Result<()> {
        if let Some(dir) = &self.tls_dir {
            std::env::set_var(lcrl_sim::remote::TLS_CA_ENV, Self::file(dir, "ca.pem")?);
            std::env::set_var(lcrl_sim::remote::TLS_CLIENT_CERT_ENV, Self::file(dir, "client.pem")?);
            std::env::set_var(lcrl_sim::remote::TLS_CLIENT_KEY_ENV, Self::file(dir, "client.key")?);
        }
        if let Some(token) = &self.token_file {
            std::env::set_var(lcrl_proto::security::TOKEN_FILE_ENV, token);
        }
        Ok(())
    }

    /// This process as a client of the run's servers.
    pub fn client(&self) -> anyhow::Result<lcrl_proto::security::ClientSecurity> {
        let (ca, cert, key) = match &self.tls_dir {
            Some(dir) => {
                let file = |name: &str| Self::file(dir, name).map(PathBuf::from).map(Some);
                (file("ca.pem")?, file("client.pem")?, file("client.key")?)
            }
            None => (None, None, None),
        };
        let identity = cert.as_deref().zip(key.as_deref());
        Ok(lcrl_proto::security::ClientSecurity::new(ca.as_deref(), identity, self.token_file.as_deref())?)
    }
}

/// Writes a new random token (32 bytes, hex), readable by its owner only.
pub fn write_token(path: &Path) -> anyhow::Result<()> {
    let mut secret = [0u8; 32];
    rand::RngCore::fill_bytes(&mut rand::rng(), &mut secret);
    let token: String = secret.iter().map(|b| format!("{b:02x}")).collect();
    write_file(path, &(token + "\n"), true)
}

/// Writes a file; secrets (keys, the token) only readable by their owner.
pub fn write_file(path: &Path, text: &str, secret: bool) -> anyhow::Result<()> {
    let mut options = std::fs::OpenOptions::new();
    options.write(true).create(true).truncate(true);
    #[cfg(unix)]
    if secret {
        std::os::unix::fs::OpenOptionsExt::mode(&mut options, 0o600);
    }
    let mut file = options.open(path).with_context(|| format!("writing {}", path.display()))?;
    std::io::Write::write_all(&mut file, text.as_bytes()).with_context(|| format!("writing {}", path.display()))
}
