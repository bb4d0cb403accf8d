//! The operator's requests to a running instance (`r2g clear`). Deliberately not part of `robo`:
//! generated code must never clear a fault.

use std::time::{Duration, Instant};

use anyhow::{bail, Context};
use ipc_schema::{process, Qos, Reply, Request, RequestKind, Services, Status};

/// Asks the runtime of `instance` to clear an `operator_required` fault; returns whether it did
/// and the runtime's reason.
pub fn clear_fault(instance: &str) -> anyhow::Result<(bool, String)> {
    let services = Services::new(instance)?;
    if process::node_alive(&process::control_node(instance)) != Some(true) {
        bail!("no r2g instance '{instance}' is running");
    }
    let pid = std::process::id();
    let node = ipc_schema::node(&format!("r2g-clear-{instance}-{pid}"))?;
    let requests = ipc_schema::open_or_create_pubsub::<Request>(&node, &services.request(), Qos::REQUESTS)?
        .publisher_builder()
        .create()
        .context("request publisher")?;
    let replies = ipc_schema::open_or_create_pubsub::<Reply>(&node, &services.reply(), Qos::REPLIES)?
        .subscriber_builder()
        .create()
        .context("reply subscriber")?;
    let wake = ipc_schema::open_or_create_event(&node, &services.control_wake())?
        .notifier_builder()
        .create()
        .context("notifier")?;
    let client = (u64::from(pid) << 32) ^ (ipc_schema::monotonic_ns() & 0xffff_ffff) ^ 0x5a5a;
    let mut sample = requests.loan_uninit().context("loan request")?;
    let p = sample.payload_mut().as_mut_ptr();
    // SAFETY: p points at a Request-sized sample we own; it is zeroed, then the fields are set.
    let sample = unsafe {
        std::ptr::write_bytes(p, 0, 1);
        (*p).id = 1;
        (*p).client = client;
        (*p).kind = RequestKind::ClearFault as u32;
        sample.assume_init()
    };
    sample.send().context("send request")?;
    wake.notify().context("wake the runtime")?;
    let t0 = Instant::now();
    while t0.elapsed() < Duration::from_secs(5) {
        while let Some(r) = replies.receive().context("reply")? {
            if r.client == client && r.id == 1 {
                return Ok((r.status == Status::Executed as u32, r.reason_str().to_string()));
            }
        }
        std::thread::sleep(Duration::from_millis(2));
    }
    bail!("the runtime of instance '{instance}' did not answer within 5 s")
}
