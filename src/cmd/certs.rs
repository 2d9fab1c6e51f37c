//! `lcrl certs`: a private CA, a server certificate for the learner and
//! graph builder, a client certificate for actors and tools, and a bearer
//! token: everything a deployment across hosts needs (rcgen).

use std::path::{Path, PathBuf};

use anyhow::{bail, Context};
use lcrl::run_security::{write_file, write_token};
use rcgen::{BasicConstraints, CertificateParams, DnType, ExtendedKeyUsagePurpose, IsCa, Issuer, KeyPair, KeyUsagePurpose};

/// Make a CA, a server and a client certificate, and a token.
#[derive(Debug, clap::Args)]
pub struct CertsArgs {
    /// Directory for ca.pem, server.pem, server.key, client.pem, client.key
    /// and token (what every pod or container mounts), and private/ca.key
    /// (the CA's key, kept out of that set: it makes new certificates).
    #[arg(long, default_value = "certs")]
    pub out: PathBuf,
    /// The names (and IP addresses) clients reach the servers by; the
    /// server certificate is valid for all of them.
    #[arg(long, value_delimiter = ',', default_value = "learner,graph-builder,localhost,127.0.0.1")]
    pub hosts: Vec<String>,
    /// Validity of the certificates, days (1 to 36500).
    #[arg(long, default_value_t = 365, value_parser = clap::value_parser!(u32).range(1..=36_500))]
    pub days: u32,
    /// Replace files already in --out.
    #[arg(long)]
    pub force: bool,
}

/// What a deployment mounts (the Secret lcrl-tls; compose's /tls).
pub const FILES: [&str; 6] = ["ca.pem", "server.pem", "server.key", "client.pem", "client.key", "token"];
const CA_KEY: &str = "private/ca.key";

pub fn run(args: &CertsArgs) -> anyhow::Result<()> {
    if args.hosts.iter().all(|h| h.trim().is_empty()) {
        bail!("--hosts must name at least one host");
    }
    if args.days == 0 {
        bail!("--days must be at least 1");
    }
    if !args.force {
        if let Some(existing) = FILES.iter().chain([&CA_KEY]).map(|f| args.out.join(f)).find(|p| p.exists()) {
            bail!("{} exists; pass --force to replace the set (clients holding the old CA will stop trusting the servers)", existing.display());
        }
    }
    let hosts: Vec<String> = args.hosts.iter().map(|h| h.trim().to_string()).filter(|h| !h.is_empty()).collect();
    write_set(&args.out, &hosts, args.days)?;
    println!("wrote {}: ca.pem, server.pem/.key (for {}), client.pem/.key, token; valid {} days", args.out.display(), hosts.join(", "), args.days);
    println!("keys and the token are readable by you only; keep {} offline (it signs new certificates)", args.out.join(CA_KEY).display());
    Ok(())
}

/// Writes a CA, a server certificate for `hosts`, a client certificate and
/// a token into `out` (also for benchmarks and tests).
pub fn write_set(out: &Path, hosts: &[String], days: u32) -> anyhow::Result<()> {
    std::fs::create_dir_all(out.join("private")).with_context(|| format!("cannot create {}", out.display()))?;
    let now = time_now();
    let until = now + time::Duration::days(i64::from(days));

    let ca_key = KeyPair::generate()?;
    let mut ca = CertificateParams::new(Vec::<String>::new())?;
    ca.distinguished_name.push(DnType::CommonName, "lcrl private CA");
    ca.is_ca = IsCa::Ca(BasicConstraints::Constrained(0));
    ca.key_usages = vec![KeyUsagePurpose::KeyCertSign, KeyUsagePurpose::CrlSign];
    (ca.not_before, ca.not_after) = (now, until);
    let ca_cert = ca.self_signed(&ca_key)?;
    let issuer = Issuer::new(ca, &ca_key);

    // The server certificate also authenticates the learner as a client
    // of the graph builder (mutual TLS), hence both purposes.
    let server_key = KeyPair::generate()?;
    let mut server = CertificateParams::new(hosts.to_vec()).context("--hosts")?;
    server.distinguished_name.push(DnType::CommonName, "lcrl server");
    server.extended_key_usages = vec![ExtendedKeyUsagePurpose::ServerAuth, ExtendedKeyUsagePurpose::ClientAuth];
    (server.not_before, server.not_after) = (now, until);
    let server_cert = server.signed_by(&server_key, &issuer)?;

    let client_key = KeyPair::generate()?;
    let mut client = CertificateParams::new(Vec::<String>::new())?;
    client.distinguished_name.push(DnType::CommonName, "lcrl client");
    client.extended_key_usages = vec![ExtendedKeyUsagePurpose::ClientAuth];
    (client.not_before, client.not_after) = (now, until);
    let client_cert = client.signed_by(&client_key, &issuer)?;

    write_file(&out.join("ca.pem"), &ca_cert.pem(), false)?;
    write_file(&out.join(CA_KEY), &ca_key.serialize_pem(), true)?;
    write_file(&out.join("server.pem"), &server_cert.pem(), false)?;
    write_file(&out.join("server.key"), &server_key.serialize_pem(), true)?;
    write_file(&out.join("client.pem"), &client_cert.pem(), false)?;
    write_file(&out.join("client.key"), &client_key.serialize_pem(), true)?;
    write_token(&out.join("token"))
}

fn time_now() -> time::OffsetDateTime {
    time::OffsetDateTime::now_utc()
}
