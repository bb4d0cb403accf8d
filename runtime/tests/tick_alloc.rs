//! The shared-memory operations of the tick, run inside a tick scope with r2g-control's
//! allocator: none may reach the system allocator. (iceoryx2 0.10 allocates a small handle per
//! loaned sample; the tick pool serves it, and this test prints how often.)

use iceoryx2::port::update_connections::UpdateConnections;
use ipc_schema::{JointCommand, Qos, SimState};
use runtime::alloc_count::{tick_allocations, tick_pool_allocations, CountingAlloc, TickScope};

#[global_allocator]
static ALLOC: CountingAlloc = CountingAlloc;

fn measure(what: &str, mut f: impl FnMut()) -> u64 {
    f(); // warm-up: first use may set things up
    let (before, pool_before) = (tick_allocations(), tick_pool_allocations());
    for _ in 0..100 {
        let _s = TickScope::enter();
        f();
    }
    let n = tick_allocations() - before;
    let pooled = tick_pool_allocations() - pool_before;
    eprintln!("{what}: {n} system allocator calls, {pooled} pool blocks in 100 calls");
    n
}

#[test]
fn the_ipc_operations_of_the_tick_do_not_allocate() {
    let node = ipc_schema::node(&format!("alloc-test-{}", std::process::id())).expect("node");
    let base = format!("r2g/alloc{}", std::process::id());
    let state =
        ipc_schema::open_or_create_pubsub::<SimState>(&node, &format!("{base}/state"), Qos::STREAM).expect("svc");
    let cmd =
        ipc_schema::open_or_create_pubsub::<JointCommand>(&node, &format!("{base}/cmd"), Qos::STREAM).expect("svc");
    let ev = ipc_schema::open_or_create_event(&node, &format!("{base}/wake")).expect("event");
    let state_pub = state.publisher_builder().create().expect("pub");
    let state_sub = state.subscriber_builder().create().expect("sub");
    let cmd_pub = cmd.publisher_builder().create().expect("pub");
    let _cmd_sub = cmd.subscriber_builder().create().expect("sub");
    let notifier = ev.notifier_builder().create().expect("notifier");
    let _listener = ev.listener_builder().create().expect("listener");
    let mut total = 0;
    total += measure("receive (empty)", || {
        let _ = state_sub.receive().expect("receive");
    });
    total += measure("send_copy + receive", || {
        state_pub.send_copy(SimState::default()).expect("send");
        let _ = state_sub.receive().expect("receive");
    });
    total += measure("send_copy to a subscriber that never reads", || {
        cmd_pub.send_copy(JointCommand::default()).expect("send");
    });
    total += measure("loan_uninit + write_payload + send", || {
        let s = cmd_pub.loan_uninit().expect("loan");
        s.write_payload(JointCommand::default()).send().expect("send");
    });
    total += measure("loan_uninit only", || {
        let s = cmd_pub.loan_uninit().expect("loan");
        drop(s);
    });
    total += measure("notify", || {
        notifier.notify().expect("notify");
    });
    total += measure("monotonic_ns", || {
        let _ = ipc_schema::monotonic_ns();
    });
    // A subscriber that connects between ticks: the publisher takes note of it inside `send`.
    let (before, _) = (tick_allocations(), 0);
    let late = state.subscriber_builder().create().expect("late subscriber");
    {
        let _s = TickScope::enter();
        state_pub.send_copy(SimState::default()).expect("send");
    }
    eprintln!("send after a new subscriber connected: {} system allocator calls", tick_allocations() - before);
    drop(late);
    // A new agent's listener: notify would register it (and allocate) inside the tick, so the
    // runtime updates connections before each deadline. The same pattern here must be clean.
    let late_listener = ev.listener_builder().create().expect("late listener");
    notifier.update_connections().expect("update");
    let before = tick_allocations();
    {
        let _s = TickScope::enter();
        notifier.notify().expect("notify");
    }
    eprintln!(
        "notify after a new listener, connections updated first: {} system allocator calls",
        tick_allocations() - before
    );
    total += tick_allocations() - before;
    drop(late_listener);
    // A new agent publishing a request.
    let requests =
        ipc_schema::open_or_create_pubsub::<ipc_schema::Request>(&node, &format!("{base}/request"), Qos::REQUESTS)
            .expect("svc");
    let req_sub = requests.subscriber_builder().create().expect("sub");
    let agent = requests.publisher_builder().create().expect("agent publisher");
    let sample = agent.loan_uninit().expect("loan");
    // SAFETY: Request is plain data; all-zero is a valid value.
    let sample = unsafe {
        std::ptr::write_bytes(sample.payload().as_ptr().cast_mut(), 0, 1);
        sample.assume_init()
    };
    sample.send().expect("send");
    req_sub.update_connections().expect("update");
    let before = tick_allocations();
    {
        let _s = TickScope::enter();
        while req_sub.receive().expect("receive").is_some() {}
    }
    eprintln!(
        "receive from a new agent, connections updated first: {} system allocator calls",
        tick_allocations() - before
    );
    total += tick_allocations() - before;
    let queue = ipc_schema::open_or_create_pubsub::<ipc_schema::Reply>(&node, &format!("{base}/reply"), Qos::REPLIES)
        .expect("svc");
    let reply_pub = queue.publisher_builder().create().expect("pub");
    let reply = ipc_schema::Reply::new(1, 1, ipc_schema::Status::Executed, "ok");
    reply_pub.send_copy(reply).expect("send");
    let before = tick_allocations();
    let late_reply_sub = queue.subscriber_builder().create().expect("late subscriber");
    {
        let _s = TickScope::enter();
        reply_pub.send_copy(reply).expect("send");
    }
    eprintln!("queue send after a new subscriber connected: {} system allocator calls", tick_allocations() - before);
    let before = tick_allocations();
    {
        let _s = TickScope::enter();
        for _ in 0..20 {
            reply_pub.send_copy(reply).expect("send");
        }
    }
    eprintln!("queue sends past the subscriber's buffer: {} system allocator calls", tick_allocations() - before);
    drop(late_reply_sub);
    assert_eq!(total, 0, "see the per-operation counts above");
}
