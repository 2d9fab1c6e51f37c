//! The `lcrl.v1.Graph` gRPC service: a thin handler over the current
//! [`GraphState`], plus health checking and server reflection
//! ([`lcrl_runtime::process::add_reflection`]).

use std::future::Future;
use std::sync::Arc;

use lcrl_proto::v1::graph_server::{Graph, GraphServer};
use lcrl_proto::v1::{ConnectionGraph, GetGraphRequest, WatchGraphRequest};
use tokio_stream::wrappers::WatchStream;
use tokio_stream::{Stream, StreamExt};
use tokio::net::TcpListener;
use tokio::sync::watch;
use lcrl_runtime::security::ServerSecurity;
use tonic::service::interceptor::InterceptedService;
use tonic::{Request, Response, Status};
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
    budget: lcrl_runtime::request_budget::RequestBudget,
    shutdown: impl Future<Output = ()> + Send + 'static,
) -> Result<(), tonic::transport::Error> {
    use lcrl_runtime::request_budget::Budgeted;
    let (health, health_service) = lcrl_runtime::process::health_service();
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
    let router = security
        .server_builder()
        .trace_fn(|req| tracing::info_span!("grpc", path = %req.uri().path()))
        .add_service(Budgeted::new(health_service, budget.clone()))
        .add_service(InterceptedService::new(
            // Its requests are empty messages: nothing larger is decoded.
            Budgeted::new(GraphServer::new(GraphService::new(state)).max_decoding_message_size(lcrl_runtime::process::SMALL_REQUEST_BYTES), budget.clone()),
            check.clone(),
        ));
    lcrl_runtime::process::add_reflection(router, &check, &budget).serve_with_incoming_shutdown(security.incoming(listener), shutdown).await
}
