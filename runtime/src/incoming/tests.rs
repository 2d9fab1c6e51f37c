//! Tests of crate::incoming: deadlines, per-peer caps and shares.

use super::*;
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio_stream::StreamExt;

fn limits(call_deadline: Duration) -> Limits {
    Limits { max_connections: 8, max_connections_per_peer: 8, idle_timeout: Duration::from_secs(60), call_deadline, refusals: Arc::default() }
}

/// A peer that keeps sending bytes (as pings do) but completes no
/// authenticated call is closed at the call deadline; one whose call
/// passed the token check is kept.
#[tokio::test]
async fn a_connection_without_an_authenticated_call_is_closed_whatever_it_sends() {
    let listener = TcpListener::bind("127.0.0.1:0").await.unwrap();
    let addr = listener.local_addr().unwrap();
    let connections = Connections::default();
    let limits = limits(Duration::from_millis(400));
    let mut accepted = incoming(listener, None, Arc::new(|| {}), limits.clone(), connections.clone());
    let chatter = |mut client: TcpStream| async move {
        // A byte every 50 ms for 1.2 s, far past the deadline.
        for _ in 0..24 {
            if client.write_all(b"x").await.is_err() {
                return;
            }
            tokio::time::sleep(Duration::from_millis(50)).await;
        }
    };
    let read_until_closed = |mut conn: Conn| async move {
        let started = std::time::Instant::now();
        let mut buf = [0u8; 16];
        loop {
            match conn.read(&mut buf).await {
                Ok(0) => return (started.elapsed(), None),
                Ok(_) => {}
                Err(e) => return (started.elapsed(), Some(e.kind())),
            }
        }
    };
    // Never called: closed after about 400 ms.
    let client = TcpStream::connect(addr).await.unwrap();
    let talker = tokio::spawn(chatter(client));
    let conn = accepted.next().await.unwrap().unwrap();
    let (lived, error) = read_until_closed(conn).await;
    assert_eq!(error, Some(io::ErrorKind::TimedOut));
    assert!(lived >= Duration::from_millis(350) && lived < Duration::from_millis(1100), "{lived:?}");
    assert_eq!(limits.refusals.no_call.load(Ordering::Relaxed), 1);
    talker.abort();
    // Called: kept until the peer hangs up.
    let client = TcpStream::connect(addr).await.unwrap();
    let peer = client.local_addr().unwrap();
    let talker = tokio::spawn(chatter(client));
    let conn = accepted.next().await.unwrap().unwrap();
    connections.mark_called(peer);
    let (lived, error) = read_until_closed(conn).await;
    talker.await.unwrap();
    assert_eq!(error, None, "closed by the peer, not the server");
    assert!(lived >= Duration::from_millis(1000), "{lived:?}");
    assert_eq!(limits.refusals.no_call.load(Ordering::Relaxed), 1);
}

/// A full server with none quiet: the peer over its share, other than
/// the newcomer's own, gives up its least recently heard connection,
/// called and busy or not; one peer holding every place too; a newcomer
/// takes nothing from its own peer; peers near their share keep theirs
/// (no two take places from each other in turn); a quiet one goes first.
#[test]
fn a_full_server_takes_a_place_from_the_peer_over_its_share() {
    let peer = |ip: &str, port: u16| SocketAddr::new(ip.parse().unwrap(), port);
    let busy = |registry: &Registry, address: SocketAddr, heard_ms: u64| {
        let hush = registry.admit(8, address);
        hush.spoken.store(true, Ordering::Release);
        hush.called.store(true, Ordering::Relaxed);
        hush.heard_ms.store(heard_ms, Ordering::Relaxed);
        hush
    };
    let evicted = |hushes: &[Arc<Hush>]| hushes.iter().filter(|h| h.evicted.load(Ordering::Acquire)).count();
    let registry = Registry::new();
    let now = registry.now_ms() + 10_000;
    // Seven places of 8 held by one host, one by another.
    let flood: Vec<_> = (0..7).map(|k| busy(&registry, peer("10.0.0.1", 100 + k), now - 10 + k as u64)).collect();
    let honest = busy(&registry, peer("10.0.0.2", 100), now - 1000);
    assert!(!registry.evict_quiet(), "none is quiet");
    assert!(!registry.evict_over_share(8, peer("10.0.0.1", 999), None), "the flood's own newcomer takes nothing");
    assert!(registry.evict_over_share(8, peer("10.0.0.3", 1), None), "a third host's newcomer");
    assert!(flood[0].evicted.load(Ordering::Acquire), "the flood's least recently heard goes");
    assert_eq!((evicted(&flood), evicted(std::slice::from_ref(&honest))), (1, 0));
    // One host holding every place: a newcomer from another takes one.
    let registry = Registry::new();
    let all: Vec<_> = (0..8).map(|k| busy(&registry, peer("10.0.0.1", 100 + k), now)).collect();
    assert!(registry.evict_over_share(8, peer("10.0.0.5", 1), None));
    assert_eq!(evicted(&all), 1);
    // Four hosts with two places each: a fifth's newcomer takes nothing
    // (the place would only move back and forth).
    let registry = Registry::new();
    let even: Vec<_> = (0..8).map(|k| busy(&registry, peer(&format!("10.0.0.{}", k / 2 + 1), 100 + k), now)).collect();
    assert!(!registry.evict_over_share(8, peer("10.0.0.9", 1), None));
    assert_eq!(evicted(&even), 0);
    // A quiet connection goes before any share is counted.
    let quiet = registry.admit(8, peer("10.0.0.9", 1));
    assert!(registry.evict_quiet());
    assert!(quiet.evicted.load(Ordering::Acquire));
}

/// One address beyond loopback holds at most its cap; others and
/// loopback are not held by it, and a closed connection frees its place.
#[test]
fn one_peer_address_holds_at_most_its_cap() {
    let registry = Registry::new();
    let peer = |ip: &str, port: u16| SocketAddr::new(ip.parse().unwrap(), port);
    let held: Vec<_> = (1..=3).map(|port| registry.admit(8, peer("10.0.0.1", port))).collect();
    assert!(registry.peer_full("10.0.0.1".parse().unwrap(), 3));
    assert!(!registry.peer_full("10.0.0.2".parse().unwrap(), 3));
    assert!(!registry.peer_full("127.0.0.1".parse().unwrap(), 0), "loopback is every local process");
    assert!(!registry.peer_full("::ffff:127.0.0.1".parse().unwrap(), 0), "also on an IPv6 listener");
    drop(held);
    assert!(!registry.peer_full("10.0.0.1".parse().unwrap(), 3), "closed connections give their places back");
}
