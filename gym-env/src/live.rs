//! An episode through a live instance (`r2g up <gym> --env`): steps, resets and images through
//! `robo`'s client, the seed and the evaluator's verdict through the sim-host's `env/`
//! services, which only an environment opens.

use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

use iceoryx2::port::listener::Listener;
use iceoryx2::port::notifier::Notifier;
use iceoryx2::port::publisher::Publisher;
use iceoryx2::port::subscriber::Subscriber;
use iceoryx2::prelude::*;
use ipc_schema::{ControlType, EnvAnswer, EnvQuery, EnvQueryKind, Services};
use pyo3::exceptions::{PyConnectionError, PyRuntimeError, PyValueError};
use pyo3::prelude::*;
use pyo3::types::{PyBytes, PyDict};
use robo::{Client, RoboError};

use crate::{control_type, limits, spec, state_dict, step_result, waypoint};

type S = ipc::Service;

/// A dead or silent instance: Python's `ConnectionError`, which the environment turns into a
/// truncated episode.
fn gone(e: impl std::fmt::Display) -> PyErr {
    PyConnectionError::new_err(e.to_string())
}

fn robo_err(e: RoboError) -> PyErr {
    match e {
        RoboError::UnknownCamera { .. } | RoboError::BadSize { .. } => PyValueError::new_err(e.to_string()),
        // The instance answers; a camera of it does not deliver: not a dead instance.
        RoboError::NoFrame(..) => PyRuntimeError::new_err(e.to_string()),
        _ => gone(e),
    }
}

/// The environment's side of the sim-host's `env/` services.
struct EnvPorts {
    queries: Publisher<S, EnvQuery, ()>,
    answers: Subscriber<S, EnvAnswer, ()>,
    sim_wake: Notifier<S>,
    wake: Listener<S>,
    next_id: u64,
    instance: String,
    _node: Node<S>,
}

impl EnvPorts {
    fn open(instance: &str) -> anyhow::Result<Self> {
        let services = Services::new(instance)?;
        let n = ipc_schema::monotonic_ns() & 0xffff_ffff;
        let node = ipc_schema::node(&format!("r2g-gym-{instance}-{}-{n}", std::process::id()))?;
        let (q, a) = sim_host::env_service::qos();
        let queries = ipc_schema::open_or_create_pubsub::<EnvQuery>(&node, &services.env_query(), q)?
            .publisher_builder()
            .create()?;
        let answers = ipc_schema::open_or_create_pubsub::<EnvAnswer>(&node, &services.env_answer(), a)?
            .subscriber_builder()
            .create()?;
        let sim_wake = ipc_schema::open_or_create_event(&node, &services.sim_wake())?.notifier_builder().create()?;
        let wake = ipc_schema::open_or_create_event(&node, &services.env_wake())?.listener_builder().create()?;
        // Ids unique across the environments of one instance: answers go to every subscriber.
        Ok(Self { queries, answers, sim_wake, wake, next_id: n << 20, instance: instance.into(), _node: node })
    }

    /// Asks and waits for the answer; an instance that does not answer within `timeout` is
    /// gone (or was started without `--env`).
    fn ask(&mut self, kind: EnvQueryKind, seed: u64, timeout: Duration) -> anyhow::Result<EnvAnswer> {
        self.next_id += 1;
        let id = self.next_id;
        self.queries.send_copy(EnvQuery { id, kind: kind as u32, _pad: 0, seed })?;
        let _ = self.sim_wake.notify();
        let t0 = Instant::now();
        loop {
            while let Some(a) = self.answers.receive()? {
                if a.id == id {
                    return Ok(*a);
                }
            }
            if t0.elapsed() > timeout {
                anyhow::bail!(
                    "the sim-host of instance '{}' did not answer within {:.0} s: it stopped, or runs without --env (start it with `r2g up <gym> --env`)",
                    self.instance,
                    timeout.as_secs_f64()
                );
            }
            let _ = self.wake.timed_wait(|_| {}, Duration::from_millis(10));
        }
    }
}

/// One episode at a time through a live instance (`r2g up <gym> --env`, wall or lockstep).
#[pyclass(unsendable, module = "r2g_gym._native")]
pub struct Live {
    client: Client,
    env: EnvPorts,
    control: ControlType,
    scene: PathBuf,
    margin_rad: f64,
    period_s: f64,
}

#[pymethods]
impl Live {
    #[new]
    #[pyo3(signature = (instance, scene, control, robot_config=None))]
    fn new(py: Python<'_>, instance: &str, scene: &str, control: &str, robot_config: Option<&str>) -> PyResult<Self> {
        let control = control_type(control)?;
        let margin_rad = limits(robot_config)?.q_margin_rad;
        // The iceoryx2 ports are bound to this thread, so the waits below keep the GIL (an
        // environment is stepped by one thread; vectors of them use one process each).
        let _ = py;
        let client = Client::connect(instance).map_err(robo_err)?;
        let env = EnvPorts::open(instance).map_err(|e| gone(format!("{e:#}")))?;
        let period_s = client.info.map_or(1e-3, |i| i.tick_period_ns as f64 * 1e-9);
        Ok(Self { client, env, control, scene: scene.into(), margin_rad, period_s })
    }

    fn spec<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyDict>> {
        spec(py, Path::new(&self.scene), self.margin_rad)
    }

    /// Seeds the next episode on the sim-host, resets through the runtime; the first state.
    fn reset<'py>(&mut self, py: Python<'py>, seed: u64) -> PyResult<Bound<'py, PyDict>> {
        let (env, client) = (&mut self.env, &mut self.client);
        env.ask(EnvQueryKind::Seed, seed, Duration::from_secs(5)).map_err(|e| gone(format!("{e:#}")))?;
        if client.reset().map_err(robo_err)? != 1 {
            // It answered: alive, but the reset did not happen (a fault, another client's chunk).
            return Err(PyRuntimeError::new_err(format!("the instance refused the reset: {}", client.feedback.reason)));
        }
        let s = client.refresh_state(Duration::from_secs(2)).map_err(robo_err)?;
        state_dict(py, &s)
    }

    fn step<'py>(
        &mut self,
        py: Python<'py>,
        action: Vec<f64>,
        ticks: u32,
    ) -> PyResult<(Bound<'py, PyDict>, Bound<'py, PyDict>)> {
        let target = waypoint(&action)?;
        let freq_hz = 1.0 / (f64::from(ticks) * self.period_s);
        let (client, control) = (&mut self.client, self.control);
        let replies = client.step(control, freq_hz, &[target], ticks).map_err(robo_err)?;
        let end = client.refresh_state(Duration::from_secs(2)).map_err(robo_err)?;
        step_result(py, control, &target, &replies, &end).map_err(gone)
    }

    fn evaluate(&mut self) -> PyResult<(bool, String)> {
        let a = self.env.ask(EnvQueryKind::Evaluate, 0, Duration::from_secs(5)).map_err(|e| gone(format!("{e:#}")))?;
        let json = String::from_utf8_lossy(&a.json[..(a.len as usize).min(a.json.len())]).into_owned();
        Ok((a.success == 1, json))
    }

    /// The newest frame of camera `name` showing the scene at the end of the last step, at
    /// `width` × `height` (resized from the camera's own size if they differ).
    fn render<'py>(&mut self, py: Python<'py>, name: &str, width: u32, height: u32) -> PyResult<Bound<'py, PyBytes>> {
        let f = self.client.frame(name, Duration::from_secs(5)).map_err(robo_err)?;
        let h = f.header();
        if (h.width, h.height) == (width, height) {
            return Ok(PyBytes::new(py, f.rgb()));
        }
        Ok(PyBytes::new(py, &robo::image::resize_rgb(f.rgb(), h.width, h.height, width, height)))
    }
}
