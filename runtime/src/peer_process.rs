//! Who holds the other end of a connection, for sharing a full server's
//! places fairly (crate::incoming): a host beyond loopback, or, on
//! loopback, the local process (Linux: /proc/net/tcp and tcp6 give the
//! peer socket's inode, /proc/PID/fd the process that holds it). Every
//! actor of `lcrl run` reaches its learner from 127.0.0.1, so the address
//! alone cannot tell one local process from another.

use std::collections::HashMap;
use std::net::{IpAddr, SocketAddr};

/// A peer as the server shares its places: a host beyond loopback, a
/// process on this host, or a local peer whose process could not be read
/// (another user's, or gone).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum PeerGroup {
    Host(IpAddr),
    Process(u32),
    Local,
}

/// The group of a peer beyond loopback (None on loopback: that takes
/// [`LocalSockets::group`]).
pub fn remote_group(peer: SocketAddr) -> Option<PeerGroup> {
    crate::limits::counted_peer(peer.ip()).map(PeerGroup::Host)
}

/// One reading of this host's TCP sockets: which inode has which local
/// address, and which process holds which socket inode.
#[derive(Debug, Default)]
pub struct LocalSockets {
    inode_of: HashMap<String, u64>,
    owner_of: HashMap<u64, u32>,
}

impl LocalSockets {
    /// Reads /proc for the processes holding the sockets of `peers` (the
    /// connecting ends of loopback connections): the TCP tables, then the
    /// processes' descriptors until every one is found. Whatever cannot be
    /// read is left out; the caller limits how often this runs.
    pub fn read_for(peers: &[SocketAddr]) -> LocalSockets {
        let mut inode_of = HashMap::new();
        for table in ["/proc/net/tcp", "/proc/net/tcp6"] {
            let Ok(text) = std::fs::read_to_string(table) else { continue };
            for line in text.lines().skip(1) {
                let fields: Vec<&str> = line.split_whitespace().collect();
                if let (Some(local), Some(inode)) = (fields.get(1), fields.get(9).and_then(|v| v.parse::<u64>().ok())) {
                    if inode != 0 {
                        inode_of.insert((*local).to_string(), inode);
                    }
                }
            }
        }
        let wanted: std::collections::HashSet<u64> = peers.iter().flat_map(|&p| proc_addresses(p)).filter_map(|a| inode_of.get(&a).copied()).collect();
        LocalSockets { owner_of: socket_owners(&wanted), inode_of }
    }

    /// The local process whose socket has address `peer`: the connecting
    /// end of a loopback connection. [`PeerGroup::Local`] when not found.
    pub fn group(&self, peer: SocketAddr) -> PeerGroup {
        proc_addresses(peer)
            .iter()
            .find_map(|address| self.inode_of.get(address))
            .and_then(|inode| self.owner_of.get(inode))
            .map_or(PeerGroup::Local, |&pid| PeerGroup::Process(pid))
    }
}

/// inode → process for the sockets `wanted`, from the descriptors of every
/// process this one may read, stopping once all are found.
fn socket_owners(wanted: &std::collections::HashSet<u64>) -> HashMap<u64, u32> {
    let mut owners = HashMap::new();
    if wanted.is_empty() {
        return owners;
    }
    let Ok(processes) = std::fs::read_dir("/proc") else { return owners };
    for process in processes.flatten() {
        let Some(pid) = process.file_name().to_str().and_then(|name| name.parse::<u32>().ok()) else { continue };
        let Ok(descriptors) = std::fs::read_dir(process.path().join("fd")) else { continue };
        for descriptor in descriptors.flatten() {
            let Ok(target) = std::fs::read_link(descriptor.path()) else { continue };
            let inode = target.to_str().and_then(|t| t.strip_prefix("socket:[")).and_then(|t| t.strip_suffix(']')).and_then(|t| t.parse::<u64>().ok());
            if let Some(inode) = inode.filter(|i| wanted.contains(i)) {
                owners.insert(inode, pid);
                if owners.len() == wanted.len() {
                    return owners;
                }
            }
        }
    }
    owners
}

/// `peer` as /proc/net/tcp{,6} write a local address: each 32-bit word of
/// the address as the host reads it (native byte order), in hex, then the
/// port. An
/// IPv4 peer may be an IPv4 socket or an IPv6 one mapping it.
fn proc_addresses(peer: SocketAddr) -> Vec<String> {
    let port = peer.port();
    let words = |octets: &[u8]| octets.chunks(4).map(|w| format!("{:08X}", u32::from_ne_bytes([w[0], w[1], w[2], w[3]]))).collect::<String>();
    match peer.ip().to_canonical() {
        IpAddr::V4(v4) => vec![format!("{}:{port:04X}", words(&v4.octets())), format!("{}:{port:04X}", words(&v4.to_ipv6_mapped().octets()))],
        IpAddr::V6(v6) => vec![format!("{}:{port:04X}", words(&v6.octets()))],
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::io::{BufRead, BufReader, Write};
    use std::process::{Command, Stdio};

    /// /proc's spelling of 127.0.0.1:8080 and of ::1 (on this
    /// little-endian machine).
    #[cfg(target_endian = "little")]
    #[test]
    fn addresses_are_written_as_proc_writes_them() {
        assert_eq!(proc_addresses("127.0.0.1:8080".parse().unwrap())[0], "0100007F:1F90");
        assert_eq!(proc_addresses("127.0.0.1:8080".parse().unwrap())[1], "0000000000000000FFFF00000100007F:1F90");
        assert_eq!(proc_addresses("[::1]:80".parse().unwrap()), vec!["00000000000000000000000001000000:0050".to_string()]);
        assert_eq!(remote_group("10.1.2.3:5".parse().unwrap()), Some(PeerGroup::Host("10.1.2.3".parse().unwrap())));
        assert_eq!(remote_group("127.0.0.1:5".parse().unwrap()), None);
    }

    /// Loopback connections from two processes (this one and a child)
    /// fall in two groups, each named by its process.
    #[test]
    fn a_loopback_peer_is_named_by_its_process() {
        let listener = std::net::TcpListener::bind("127.0.0.1:0").unwrap();
        let port = listener.local_addr().unwrap().port();
        let script = format!("import socket,sys\ns=socket.create_connection(('127.0.0.1',{port}))\nprint('connected',flush=True)\nsys.stdin.read()\n");
        let mut child = Command::new("python3").args(["-c", &script]).stdin(Stdio::piped()).stdout(Stdio::piped()).spawn().expect("python3 runs");
        let mut line = String::new();
        BufReader::new(child.stdout.take().unwrap()).read_line(&mut line).unwrap();
        let (_from_child, child_peer) = listener.accept().unwrap();
        let _mine = std::net::TcpStream::connect(("127.0.0.1", port)).unwrap();
        let (_from_me, my_peer) = listener.accept().unwrap();
        let sockets = LocalSockets::read_for(&[child_peer, my_peer]);
        assert_eq!(sockets.group(child_peer), PeerGroup::Process(child.id()));
        assert_eq!(sockets.group(my_peer), PeerGroup::Process(std::process::id()));
        assert_eq!(sockets.group("127.0.0.1:1".parse().unwrap()), PeerGroup::Local, "no such socket");
        let _ = child.stdin.take().unwrap().write_all(b"");
        let _ = child.kill();
        let _ = child.wait();
    }
}
