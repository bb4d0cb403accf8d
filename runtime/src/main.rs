//! r2g-control: the hard-ticked control process of one gym instance.

/// Counts allocations made inside ticks; the figure is in the tick statistics.
#[global_allocator]
static ALLOC: runtime::alloc_count::CountingAlloc = runtime::alloc_count::CountingAlloc;

fn main() {
    std::process::exit(runtime::control_main::main(None));
}
