//! The `lcrl.v1.Graph` gRPC service: a thin handler over the current
//! [`GraphState`], plus health checking and server reflection.

use std::future::Future;
use std::sync::Arc;

use lcrl_proto::v1::graph_server::{Graph, GraphServer};
use lcrl_proto::v1::{ConnectionGraph, GetGraphRequest, WatchGraphRequest};
use tokio_stream::wrappers::WatchStream;
use tokio_stream::{Stream, StreamExt};
use tokio::net::TcpListener;
use tokio::sync::watch;
use lcrl_proto::security::{ServerSecurity, TokenCheck};
use tonic::service::interceptor::InterceptedService;
use tonic::{Request, Response, Status};
use tonic_reflection::server as reflection;
use tonic_health::ServingStatus;

/// What the service has to offer right now.
#[derive(Debug, Clone)]
pub enum GraphState {
    /// No graph and none coming (NOT_FOUND).
    Empty,
    /// CS3 is running (UNAVAILABLE).
    Building,
    Ready(Arc<ConnectionGraph>),
}

/// Answers `GetGraph` from a watch channel the builder writes to.
#[derive(Debug, Clone)]
pub struct GraphService {
    state: watch::Receiver<GraphState>,
}

impl GraphService {
    pub fn new(state: watch::Receiver<GraphState>) -> Self {
        GraphService { state }
    }
}

/// The stream of `WatchGraph`: each Ready state of the watch channel.
pub type GraphStream = std::pin::Pin<Box<dyn Stream<Item = Result<ConnectionGraph, Status>> + Send>>;

#[tonic::async_trait]
impl Graph for GraphService {
    type WatchGraphStream = GraphStream;

    #[tracing::instrument(skip_all, name = "WatchGraph")]
    async fn watch_graph(&self, _request: Request<WatchGraphRequest>) -> Result<Response<GraphStream>, Status> {
        let stream = WatchStream::new(self.state.clone()).filter_map(|state| match state {
            GraphState::Ready(graph) => Some(Ok((*graph).clone())),
            _ => None,
        });
        Ok(Response::new(Box::pin(stream)))
    }

    #[tracing::instrument(skip_all, name = "GetGraph")]
    async fn get_graph(&self, _request: Request<GetGraphRequest>) -> Result<Response<ConnectionGraph>, Status> {
        let state = self.state.borrow().clone();
        match state {
            GraphState::Ready(graph) => Ok(Response::new((*graph).clone())),
            GraphState::Building => Err(Status::unavailable("the connection graph is still being built; retry shortly")),
            GraphState::Empty => Err(Status::not_found("this service holds no connection graph")),
        }
    }
}

/// Serves Graph, grpc.health.v1 and reflection (v1 and v1alpha) on
/// `listener` until `shutdown` resolves, with TLS where `security` says;
/// its token check guards every service but health. Health reports NOT_SERVING (for "" and for
/// lcrl.v1.Graph) until the state becomes Ready.
pub async fn serve(
    listener: TcpListener,
    state: watch::Receiver<GraphState>,
    security: ServerSecurity,
    shutdown: impl Future<Output = ()> + Send + 'static,
) -> Result<(), tonic::transport::Error> {
    let (health, health_service) = tonic_health::server::health_reporter();
    let graph_name = <GraphServer<GraphService> as tonic::server::NamedService>::NAME;
    let mut watcher = state.clone();
    let ready = |w: &mut watch::Receiver<GraphState>| {
        let status = matches!(*w.borrow_and_update(), GraphState::Ready(_));
        if status { ServingStatus::Serving } else { ServingStatus::NotServing }
    };
    // Set before the first connection is accepted, so no client ever sees
    // the reporter's default SERVING for "" while the graph is missing.
    let status = ready(&mut watcher);
    health.set_service_status("", status).await;
    health.set_service_status(graph_name, status).await;
    tokio::spawn(async move {
        while watcher.changed().await.is_ok() {
            let status = ready(&mut watcher);
            health.set_service_status("", status).await;
            health.set_service_status(graph_name, status).await;
        }
    });
    let check = security.token_check();
    let router = tonic::transport::Server::builder()
        .trace_fn(|req| tracing::info_span!("grpc", path = %req.uri().path()))
        .add_service(health_service)
        .add_service(InterceptedService::new(GraphServer::new(GraphService::new(state)), check.clone()));
    add_reflection(router, &check).serve_with_incoming_shutdown(security.incoming(listener), shutdown).await
}

/// Adds server reflection of lcrl.v1 and grpc.health.v1 in both protocol
/// versions, behind the token check: v1 (grpcurl, grpcui, newer tools) and
/// v1alpha (grpcio's `grpcio-reflection`, Postman, older tools).
pub fn add_reflection<L>(router: tonic::transport::server::Router<L>, check: &TokenCheck) -> tonic::transport::server::Router<L> {
    let configure = || {
        reflection::Builder::configure()
            .register_encoded_file_descriptor_set(lcrl_proto::v1::FILE_DESCRIPTOR_SET)
            .register_encoded_file_descriptor_set(tonic_health::pb::FILE_DESCRIPTOR_SET)
    };
    // The descriptor sets are compiled in: a failure is a build defect,
    // which every test that starts a server would show.
    let v1 = configure().build_v1().expect("compiled-in descriptor sets are valid");
    let v1alpha = configure().build_v1alpha().expect("compiled-in descriptor sets are valid");
    router.add_service(InterceptedService::new(v1, check.clone())).add_service(InterceptedService::new(v1alpha, check.clone()))
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
