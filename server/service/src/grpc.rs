//! The gRPC services (tonic): thin handlers that check the request into domain values,
//! hand over to the session, and answer.

use std::collections::VecDeque;
use std::pin::Pin;
use std::sync::atomic::{AtomicBool, AtomicU32, AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use std::task::{Context, Poll};

use cutsim_proto::v1 as pb;
use cutsim_proto::v1::haptics_server::Haptics;
use cutsim_proto::v1::scripts_server::Scripts;
use cutsim_proto::v1::sessions_server::Sessions;
use cutsim_sim::hash::hash_hex;
use cutsim_sim::script::CutScript;
use cutsim_sim::tool::ToolCommand;
use futures_util::{Stream, StreamExt};
use tonic::{Request, Response, Status, Streaming};

use crate::auth::{Caller, Operator, Role, SESSION_KEY, TOKEN_KEY};
use crate::convert;
use crate::rate::TokenBucket;
use crate::error::ApiError;
use crate::session::records::{FeedbackRecord, StampedCommand};
use crate::session::{CloseReason, Creator, Mode, Registry, SceneSource, ScriptEvent, Session};

/// The state every service shares.
#[derive(Clone)]
pub struct Api {
    pub registry: Arc<Registry>,
}

fn metadata<'a, T>(request: &'a Request<T>, key: &str) -> Option<&'a str> {
    request.metadata().get(key).and_then(|v| v.to_str().ok())
}

/// Who is calling: the token, the peer and whether its TLS client certificate is an
/// operator's.
fn caller<T>(request: &Request<T>) -> Caller<'_> {
    Caller {
        token: metadata(request, TOKEN_KEY),
        peer: request.remote_addr(),
        operator_certificate: request.peer_certs().is_some_and(|certs| !certs.is_empty()),
    }
}

impl Api {
    /// A session the caller may use with `needed`: its own token, or — to watch it — an
    /// operator's credentials.
    fn session<T>(&self, id: &str, request: &Request<T>, needed: Role) -> Result<Arc<Session>, ApiError> {
        let session = self.registry.get(id)?;
        if let Err(e) = session.authorize(metadata(request, TOKEN_KEY), needed) {
            if needed != Role::Observe || self.registry.operators.authenticate(&caller(request)).is_err() {
                return Err(e);
            }
        }
        session.touch();
        Ok(session)
    }

    fn operator<T>(&self, request: &Request<T>) -> Result<Operator, ApiError> {
        self.registry.operators.authenticate(&caller(request))
    }
}

#[tonic::async_trait]
impl Sessions for Api {
    async fn create_session(&self, request: Request<pb::CreateSessionRequest>) -> Result<Response<pb::CreateSessionResponse>, Status> {
        let operator = self.operator(&request)?;
        let r = request.into_inner();
        let source = match r.scene {
            Some(pb::create_session_request::Scene::SceneName(name)) => SceneSource::Bundled(name),
            Some(pb::create_session_request::Scene::SceneJson(json)) => SceneSource::Inline(json),
            None => return Err(ApiError::InvalidArgument("give scene_name (a bundled scene) or scene_json".into()).into()),
        };
        let mode = if r.mode == pb::SessionMode::Lockstep as i32 { Mode::Lockstep } else { Mode::Realtime };
        let session = self.registry.create(source, mode, r.label, Creator { who: operator.to_string(), expires: true }).await?;
        let (control, observe) = session.tokens();
        Ok(Response::new(pb::CreateSessionResponse {
            session: Some(convert::session_info(&session)),
            control_token: control.to_owned(),
            observe_token: observe.to_owned(),
        }))
    }

    async fn list_sessions(&self, request: Request<pb::ListSessionsRequest>) -> Result<Response<pb::ListSessionsResponse>, Status> {
        self.operator(&request)?;
        let sessions = self.registry.list().iter().map(|s| convert::session_info(s)).collect();
        Ok(Response::new(pb::ListSessionsResponse { sessions }))
    }

    async fn get_session(&self, request: Request<pb::GetSessionRequest>) -> Result<Response<pb::SessionInfo>, Status> {
        let session = self.session(&request.get_ref().session_id, &request, Role::Observe)?;
        let mut info = convert::session_info(&session);
        if request.get_ref().with_state_hash {
            let (step, hash) = session.state_hash().await?;
            info.state_hash = hash_hex(hash);
            info.state_hash_step = step;
        }
        Ok(Response::new(info))
    }

    /// The session's control token closes it; an operator closes any session.
    async fn close_session(&self, request: Request<pb::CloseSessionRequest>) -> Result<Response<pb::CloseSessionResponse>, Status> {
        let id = &request.get_ref().session_id;
        if let Err(e) = self.session(id, &request, Role::Control) {
            let operator = self.operator(&request).map_err(|_| e)?;
            self.registry.get(id)?;
            tracing::info!(session = %id, by = %operator, "an operator closes the session");
        }
        self.registry.close(id, CloseReason::Closed).await?;
        Ok(Response::new(pb::CloseSessionResponse {}))
    }

    async fn get_snapshot(&self, request: Request<pb::GetSnapshotRequest>) -> Result<Response<pb::Snapshot>, Status> {
        let session = self.session(&request.get_ref().session_id, &request, Role::Observe)?;
        let (snapshot, step) = session.snapshot().await?;
        Ok(Response::new(convert::snapshot(&snapshot, &session.id, step)))
    }

    async fn get_assessment(&self, request: Request<pb::GetAssessmentRequest>) -> Result<Response<pb::Assessment>, Status> {
        let session = self.session(&request.get_ref().session_id, &request, Role::Observe)?;
        Ok(Response::new(convert::session_assessment(&session)))
    }
}

/// What the command reader and the feedback stream of one haptic client share.
struct HapticClient {
    session: Arc<Session>,
    slot: usize,
    /// Bit t set: the client has commanded tool t.
    tools: AtomicU64,
    every: AtomicU32,
    error: Mutex<Option<Status>>,
    done: AtomicBool,
}

impl HapticClient {
    fn fail(&self, status: Status) {
        *self.error.lock().expect("error lock") = Some(status);
        self.session.subscribers.wake(self.slot);
    }

    fn finish(&self) {
        self.done.store(true, Ordering::Release);
        self.session.subscribers.wake(self.slot);
    }
}

/// Streams feedback to one haptic client: woken by the physics thread after each step,
/// it sends the newest feedback of each of the client's tools, every `every` steps.
/// A client slower than that gets the newest only: nothing queues.
struct FeedbackStream {
    client: Arc<HapticClient>,
    last_step: Option<u64>,
    pending: VecDeque<pb::ForceFeedback>,
    ended: bool,
}

impl Stream for FeedbackStream {
    type Item = Result<pb::ForceFeedback, Status>;

    fn poll_next(mut self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<Option<Self::Item>> {
        if self.ended {
            return Poll::Ready(None);
        }
        if let Some(next) = self.pending.pop_front() {
            return Poll::Ready(Some(Ok(next)));
        }
        let client = self.client.clone();
        client.session.subscribers.register(client.slot, cx.waker());
        if let Some(status) = client.error.lock().expect("error lock").take() {
            self.ended = true;
            return Poll::Ready(Some(Err(status)));
        }
        if let Some(e) = client.session.failed_error() {
            self.ended = true;
            return Poll::Ready(Some(Err(e.into())));
        }
        if client.done.load(Ordering::Acquire) || client.session.is_closed() {
            self.ended = true;
            return Poll::Ready(None);
        }
        let tools = client.tools.load(Ordering::Acquire);
        let every = u64::from(client.every.load(Ordering::Relaxed).max(1));
        for tool in (0..client.session.feedback.len()).filter(|t| tools & (1 << t) != 0) {
            let (words, version) = client.session.feedback[tool].read();
            if version == 0 {
                continue;
            }
            let r = FeedbackRecord::from_words(&words);
            let due = self.last_step.is_none_or(|last| r.step >= last + every);
            if due {
                self.pending.push_back(pb::ForceFeedback {
                    step: r.step,
                    force_n: Some(convert::vec3(&r.feedback.force_n)),
                    torque_nm: Some(convert::vec3(&r.feedback.torque_nm)),
                    contacts: r.feedback.contacts,
                    cutting: r.feedback.cutting,
                    force_clamped: r.feedback.force_clamped,
                    echo_client_time_ns: r.echo_client_time_ns,
                    server_latency_us: r.server_latency_ns as f64 / 1e3,
                    step_time_us: r.step_time_ns as f64 / 1e3,
                    tool: tool as u32,
                    resistance_n: Some(convert::vec3(&r.feedback.resistance_n)),
                    grasping: r.feedback.grasping,
                    jaws_force_n: r.feedback.jaws_force_n,
                });
            }
        }
        if let Some(step) = self.pending.iter().map(|f| f.step).max() {
            self.last_step = Some(step);
        }
        match self.pending.pop_front() {
            Some(next) => Poll::Ready(Some(Ok(next))),
            None => Poll::Pending,
        }
    }
}

impl Drop for FeedbackStream {
    fn drop(&mut self) {
        self.client.session.subscribers.leave(self.client.slot);
    }
}

#[tonic::async_trait]
impl Haptics for Api {
    type StreamStream = Pin<Box<dyn Stream<Item = Result<pb::ForceFeedback, Status>> + Send>>;

    async fn stream(&self, request: Request<Streaming<pb::ToolCommand>>) -> Result<Response<Self::StreamStream>, Status> {
        let id = metadata(&request, SESSION_KEY)
            .ok_or_else(|| ApiError::InvalidArgument(format!("name the session in the metadata key `{SESSION_KEY}`")))?
            .to_owned();
        let session = self.session(&id, &request, Role::Control)?;
        if let Some(e) = session.failed_error() {
            return Err(e.into());
        }
        let slot = session.subscribers.join().ok_or_else(|| {
            ApiError::exhausted(
                "haptic clients",
                format!("session {id} already has its maximum of {} haptic clients", self.registry.config.limits.max_haptic_clients_per_session),
            )
        })?;
        let client = Arc::new(HapticClient {
            session,
            slot,
            tools: AtomicU64::new(0),
            every: AtomicU32::new(1),
            error: Mutex::new(None),
            done: AtomicBool::new(false),
        });
        let margin = self.registry.config.limits.pose_margin_m;
        let per_second = self.registry.config.limits.tool_commands_per_second;
        // Two seconds' worth saved up: a stream held up by the network may arrive in a rush.
        let mut rate = TokenBucket::new(per_second, 2.0 * per_second, std::time::Instant::now());
        let mut commands = request.into_inner();
        let reader = client.clone();
        tokio::spawn(async move {
            let mut last: Vec<Option<StampedCommand>> = vec![None; reader.session.tools.len()];
            loop {
                match commands.next().await {
                    Some(Ok(command)) => {
                        if let Err(wait) = rate.take(std::time::Instant::now()) {
                            let e = ApiError::RateLimited {
                                message: format!(
                                    "more than {per_second} tool commands per second on one stream (the physics steps at 1 kHz: one command per step is all it uses)"
                                ),
                                retry_after: wait,
                            };
                            reader.fail(e.into());
                            break;
                        }
                        let received = reader.session.now_ns();
                        match convert::tool_command(&command, &reader.session, received, margin) {
                            Ok((tool, stamped)) => {
                                reader.every.store(stamped.feedback_every, Ordering::Relaxed);
                                reader.tools.fetch_or(1 << tool, Ordering::AcqRel);
                                reader.session.submit(tool, stamped);
                                reader.session.touch();
                                last[tool] = Some(stamped);
                            }
                            Err(e) => {
                                tracing::debug!(session = %reader.session.id, error = %e, "haptic command refused");
                                reader.fail(e.into());
                                break;
                            }
                        }
                    }
                    Some(Err(status)) => {
                        tracing::debug!(session = %reader.session.id, %status, "haptic stream broke");
                        break;
                    }
                    None => break,
                }
            }
            // The client is gone or refused: its tools leave the scene.
            for (tool, command) in last.iter().enumerate() {
                if let Some(stamped) = command {
                    let away = StampedCommand { command: ToolCommand { active: false, cut: false, ..stamped.command }, ..*stamped };
                    reader.session.submit(tool, away);
                }
            }
            reader.finish();
        });
        let stream = FeedbackStream { client, last_step: None, pending: VecDeque::new(), ended: false };
        Ok(Response::new(Box::pin(stream)))
    }
}

#[tonic::async_trait]
impl Scripts for Api {
    type RunScriptStream = Pin<Box<dyn Stream<Item = Result<pb::ScriptEvent, Status>> + Send>>;

    async fn run_script(&self, request: Request<pb::RunScriptRequest>) -> Result<Response<Self::RunScriptStream>, Status> {
        let session = self.session(&request.get_ref().session_id, &request, Role::Control)?;
        let r = request.into_inner();
        let limits = &self.registry.config.limits;
        if r.script_json.len() > limits.max_script_bytes {
            return Err(ApiError::exhausted("script size", format!("script_json is {} bytes; at most {} are allowed", r.script_json.len(), limits.max_script_bytes)).into());
        }
        let script = CutScript::from_json_str(&r.script_json, "script_json").map_err(script_error)?;
        let compiled = script.compile(&session.tools, 1.0 / session.rate_hz, "script_json").map_err(script_error)?;
        if compiled.steps > limits.max_script_steps {
            return Err(ApiError::exhausted("script steps", format!("the script runs {} steps; at most {} are allowed", compiled.steps, limits.max_script_steps)).into());
        }
        let (tx, rx) = tokio::sync::mpsc::unbounded_channel();
        session.send_control(crate::session::Control::RunScript { script: compiled, progress_every: r.progress_every_steps, events: tx })?;
        let task = session.assessment.task.clone();
        let events = tokio_stream_from(rx).map(move |event| match event {
            ScriptEvent::Progress(p) => Ok(pb::ScriptEvent { event: Some(pb::script_event::Event::Progress(convert::progress(&p))) }),
            ScriptEvent::Report(report) => Ok(pb::ScriptEvent { event: Some(pb::script_event::Event::Report(convert::report(&report, &task))) }),
            ScriptEvent::Failed(message) => Err(Status::unavailable(message)),
        });
        // The physics thread may die mid-script: the stream then ends with its reason
        // rather than without a report.
        let ended = futures_util::stream::once(async move {
            session.settled().await;
            let e = session.failed_error().unwrap_or_else(|| ApiError::Unavailable(format!("session {} stopped before the script's report", session.id)));
            Err::<pb::ScriptEvent, Status>(e.into())
        });
        let events = until_the_run_ends(events, ended);
        Ok(Response::new(Box::pin(events)))
    }
}

/// A script's events, then `ended` only if none of them ended the run: the stream ends
/// right after the event that does (a report or an error) without polling on. (Polling on
/// past the report made every script's stream wait for `ended`, whose wait for the session
/// to settle gives up after a second.)
fn until_the_run_ends<E, F>(events: E, ended: F) -> impl Stream<Item = Result<pb::ScriptEvent, Status>> + Send
where
    E: Stream<Item = Result<pb::ScriptEvent, Status>> + Send + 'static,
    F: Stream<Item = Result<pb::ScriptEvent, Status>> + Send + 'static,
{
    let mut events = Box::pin(events.chain(ended));
    let mut done = false;
    futures_util::stream::poll_fn(move |cx| {
        if done {
            return Poll::Ready(None);
        }
        events.as_mut().poll_next(cx).map(|event| {
            let event = event?;
            done = matches!(&event, Ok(pb::ScriptEvent { event: Some(pb::script_event::Event::Report(_)) }) | Err(_));
            Some(event)
        })
    })
}

/// A script that cannot be used: the JSON path of what is wrong, as a field violation.
fn script_error(e: cutsim_sim::scene::SceneError) -> ApiError {
    ApiError::BadField { request_field: "script_json", field: e.path.clone(), message: e.to_string() }
}

/// An unbounded receiver as a stream.
fn tokio_stream_from<T: Send + 'static>(mut rx: tokio::sync::mpsc::UnboundedReceiver<T>) -> impl Stream<Item = T> + Send {
    futures_util::stream::poll_fn(move |cx| rx.poll_recv(cx))
}

#[cfg(test)]
mod tests {
    use super::*;
    use futures_util::FutureExt;

    fn progress() -> Result<pb::ScriptEvent, Status> {
        Ok(pb::ScriptEvent { event: Some(pb::script_event::Event::Progress(pb::ScriptProgress::default())) })
    }

    fn report() -> Result<pb::ScriptEvent, Status> {
        Ok(pb::ScriptEvent { event: Some(pb::script_event::Event::Report(pb::ScriptReport::default())) })
    }

    /// A fallback that never comes (a session that never settles).
    fn never() -> impl Stream<Item = Result<pb::ScriptEvent, Status>> + Send {
        futures_util::stream::pending()
    }

    #[test]
    fn a_script_stream_ends_with_its_report_without_waiting_for_the_fallback() {
        // The event channel stays open after the report, and the fallback never comes:
        // the stream still ends at once.
        let events = futures_util::stream::iter([progress(), report()]).chain(futures_util::stream::pending());
        let mut stream = Box::pin(until_the_run_ends(events, never()));
        assert!(matches!(stream.next().now_or_never(), Some(Some(Ok(pb::ScriptEvent { event: Some(pb::script_event::Event::Progress(_)) })))));
        assert!(matches!(stream.next().now_or_never(), Some(Some(Ok(pb::ScriptEvent { event: Some(pb::script_event::Event::Report(_)) })))));
        assert!(matches!(stream.next().now_or_never(), Some(None)), "ended right after the report");
    }

    #[test]
    fn a_script_stream_ends_with_an_error_or_else_with_the_fallback() {
        let failed = futures_util::stream::iter([progress(), Err(Status::unavailable("stopped"))]);
        let mut stream = Box::pin(until_the_run_ends(failed, never()));
        assert!(matches!(stream.next().now_or_never(), Some(Some(Ok(_)))));
        assert!(matches!(stream.next().now_or_never(), Some(Some(Err(_)))));
        assert!(matches!(stream.next().now_or_never(), Some(None)), "ended right after the error");

        // Events that end without a report: the fallback's error closes the stream.
        let cut_short = futures_util::stream::iter([progress()]);
        let fallback = futures_util::stream::iter([Err(Status::internal("the physics stopped"))]);
        let mut stream = Box::pin(until_the_run_ends(cut_short, fallback));
        assert!(matches!(stream.next().now_or_never(), Some(Some(Ok(_)))));
        assert!(matches!(stream.next().now_or_never(), Some(Some(Err(e))) if e.code() == tonic::Code::Internal));
        assert!(matches!(stream.next().now_or_never(), Some(None)));
    }
}
