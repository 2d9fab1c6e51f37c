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
            std::env::set_var(lcrl_runtime::security::TOKEN_FILE_ENV, token);
        }
        Ok(())
    }

    /// This process as a client of the run's servers.
    pub fn client(&self) -> anyhow::Result<lcrl_runtime::security::ClientSecurity> {
        let (ca, cert, key) = match &self.tls_dir {
            Some(dir) => {
                let file = |name: &str| Self::file(dir, name).map(PathBuf::from).map(Some);
                (file("ca.pem")?, file("client.pem")?, file("client.key")?)
            }
            None => (None, None, None),
        };
        let identity = cert.as_deref().zip(key.as_deref());
        Ok(lcrl_runtime::security::ClientSecurity::new(ca.as_deref(), identity, self.token_file.as_deref())?)
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
    if secret {
        return write_secret(path, text);
    }
    let mut options = std::fs::OpenOptions::new();
    options.write(true).create(true).truncate(true);
    let mut file = options.open(path).with_context(|| format!("writing {}", path.display()))?;
    std::io::Write::write_all(&mut file, text.as_bytes()).with_context(|| format!("writing {}", path.display()))
}

/// A secret written safely (issue 82): never through a symbolic link,
/// never over a file others could have read (refused, with the command
/// that fixes it), always owner-only. The text goes to a new file created
/// beside it with mode 0600 (O_EXCL, O_NOFOLLOW), then renamed over the
/// path, so no moment exists at which it is readable by others.
fn write_secret(path: &Path, text: &str) -> anyhow::Result<()> {
    #[cfg(unix)]
    {
        use std::os::unix::fs::{MetadataExt, OpenOptionsExt};
        match std::fs::symlink_metadata(path) {
            Ok(meta) if meta.file_type().is_symlink() => {
                bail!("{} is a symbolic link; a secret is never written through one. Remove it (rm {}) and run again", path.display(), path.display())
            }
            Ok(meta) if meta.mode() & 0o077 != 0 => bail!(
                "{} exists with mode {:o}: others may have read it. Remove it (rm {}) and run again for a new one, or make it owner-only (chmod 600 {}) if nobody else could read it",
                path.display(),
                meta.mode() & 0o777,
                path.display(),
                path.display()
            ),
            _ => {}
        }
        let dir = path.parent().filter(|d| !d.as_os_str().is_empty()).unwrap_or(Path::new("."));
        let name = path.file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_else(|| "secret".into());
        let staging = dir.join(format!(".{name}.{}.new", std::process::id()));
        let mut file = std::fs::OpenOptions::new()
            .write(true)
            .create_new(true)
            .mode(0o600)
            .custom_flags(libc::O_NOFOLLOW)
            .open(&staging)
            .with_context(|| format!("writing {}", staging.display()))?;
        let written = std::io::Write::write_all(&mut file, text.as_bytes())
            .and_then(|()| file.sync_all())
            .with_context(|| format!("writing {}", staging.display()))
            .and_then(|()| std::fs::rename(&staging, path).with_context(|| format!("moving {} to {}", staging.display(), path.display())));
        if written.is_err() {
            // Nothing half-written is left beside the target.
            let _ = std::fs::remove_file(&staging);
        }
        written
    }
    #[cfg(not(unix))]
    {
        std::fs::write(path, text).with_context(|| format!("writing {}", path.display()))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::os::unix::fs::{MetadataExt, PermissionsExt};

    /// A token is owner-only, new or replacing an owner-only one; a link is
    /// never followed and a file others could read is refused with the fix.
    #[test]
    fn tokens_are_written_owner_only_never_through_a_link_nor_over_a_loose_file() {
        let dir = tempfile::tempdir().unwrap();
        let token = dir.path().join("token");
        write_token(&token).unwrap();
        let first = std::fs::read_to_string(&token).unwrap();
        assert_eq!(std::fs::metadata(&token).unwrap().mode() & 0o777, 0o600);
        write_token(&token).unwrap();
        assert_ne!(std::fs::read_to_string(&token).unwrap(), first, "a new token replaces the old one");
        assert_eq!(std::fs::metadata(&token).unwrap().mode() & 0o777, 0o600);

        std::fs::set_permissions(&token, std::fs::Permissions::from_mode(0o644)).unwrap();
        let before = std::fs::read_to_string(&token).unwrap();
        let err = write_token(&token).unwrap_err().to_string();
        assert!(err.contains("mode 644") && err.contains(&format!("chmod 600 {}", token.display())), "{err}");
        assert_eq!(std::fs::read_to_string(&token).unwrap(), before, "a refused write leaves the file as it was");

        let elsewhere = dir.path().join("world-readable");
        std::fs::write(&elsewhere, "").unwrap();
        std::fs::set_permissions(&elsewhere, std::fs::Permissions::from_mode(0o666)).unwrap();
        let link = dir.path().join("linked-token");
        std::os::unix::fs::symlink(&elsewhere, &link).unwrap();
        let err = write_token(&link).unwrap_err().to_string();
        assert!(err.contains("is a symbolic link"), "{err}");
        assert_eq!(std::fs::read_to_string(&elsewhere).unwrap(), "", "nothing was written through the link");
        assert!(std::fs::read_dir(dir.path()).unwrap().flatten().all(|e| !e.file_name().to_string_lossy().ends_with(".new")), "no staging file left");
    }
}
