//! `lcrl-graph-builder` as a real process, queried by a real gRPC client.

use std::process::Child;
use std::time::{Duration, Instant};

use lcrl_proto::v1::graph_client::GraphClient;
use lcrl_proto::v1::GetGraphRequest;
use tonic_health::pb::health_check_response::ServingStatus;
use tonic_health::pb::health_client::HealthClient;
use tonic_health::pb::HealthCheckRequest;

use super::common::{spawn_listening, workspace_bin};

/// A running graph builder, killed when dropped.
struct Server {
    child: Child,
    url: String,
}

impl Drop for Server {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

fn start(samples: &str) -> Server {
    let (child, addr) = spawn_listening(workspace_bin("lcrl-graph-builder").args(["--env", "lti-paper", "--samples", samples, "--listen", "127.0.0.1:0"]));
    Server { url: format!("http://{addr}"), child }
}

async fn health(url: &str, service: &str) -> ServingStatus {
    let channel = tonic::transport::Channel::from_shared(url.to_string()).unwrap().connect().await.unwrap();
    let mut client = HealthClient::new(channel);
    let request = HealthCheckRequest { service: service.into() };
    let status = client.check(request).await.unwrap().into_inner().status;
    ServingStatus::try_from(status).unwrap()
}

#[tokio::test]
async fn serves_the_graph_and_health_once_built() {
    let server = start("64");
    let deadline = Instant::now() + Duration::from_secs(60);
    while health(&server.url, "lcrl.v1.Graph").await != ServingStatus::Serving {
        assert!(Instant::now() < deadline, "graph builder never became healthy");
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
    assert_eq!(health(&server.url, "").await, ServingStatus::Serving);
    let mut client = GraphClient::connect(server.url.clone()).await.unwrap();
    let graph = client.get_graph(GetGraphRequest {}).await.unwrap().into_inner();
    assert_eq!((graph.actions, graph.states), (3, 3));
    assert_eq!(graph.g, vec![1, 0, 0, 1, 1, 0, 0, 0, 1]);
    assert_eq!(graph.state_names, vec!["s1", "s2", "s3"]);
    assert_eq!(graph.samples, 64);
    // WatchGraph delivers the built graph at once.
    let mut watch = client.watch_graph(lcrl_proto::v1::WatchGraphRequest {}).await.unwrap().into_inner();
    let first = tokio::time::timeout(Duration::from_secs(10), watch.message()).await.unwrap().unwrap().unwrap();
    assert_eq!(first.g, graph.g);
}

#[tokio::test]
async fn unavailable_and_not_serving_while_building() {
    // 2·10^6 samples per action take seconds to build (and ~150 MB); the
    // queries below run in milliseconds, while the build is still going.
    let server = start("2000000");
    let mut client = GraphClient::connect(server.url.clone()).await.unwrap();
    let status = client.get_graph(GetGraphRequest {}).await.unwrap_err();
    assert_eq!(status.code(), tonic::Code::Unavailable, "{status:?}");
    assert_eq!(health(&server.url, "lcrl.v1.Graph").await, ServingStatus::NotServing);
}

#[test]
fn bad_arguments_exit_before_serving() {
    let out = workspace_bin("lcrl-graph-builder").args(["--env", "nope", "--listen", "127.0.0.1:0"]).output().unwrap();
    super::common::assert_clean_failure(&out, "unknown environment 'nope'");
}
