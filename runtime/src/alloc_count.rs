//! The tick's allocations, measured and contained.
//!
//! r2g-control installs [`CountingAlloc`] as its global allocator and the wall loop marks each
//! tick with [`TickScope`]. Our own tick code allocates nothing, but iceoryx2 0.10 creates a
//! small reference-counted handle for every loaned sample (one allocation and one free per
//! publish). Inside a tick those small requests are served from a preallocated, lock-free pool
//! of fixed blocks: bounded time, no lock, no system call, no malloc. Anything that still
//! reaches the system allocator from a tick is counted in [`tick_allocations`], which the tick
//! statistics report and a test requires to be zero. Frees of system memory are counted apart
//! ([`tick_frees`]): the one known source is iceoryx2 dropping a dead peer's connection.

use std::alloc::{GlobalAlloc, Layout, System};
use std::cell::{Cell, UnsafeCell};
use std::sync::atomic::{AtomicBool, AtomicU64, AtomicUsize, Ordering};

const BLOCK_BYTES: usize = 256;
const BLOCK_ALIGN: usize = 64;
const BLOCKS: usize = 128;

#[repr(C, align(64))]
struct Block(UnsafeCell<[u8; BLOCK_BYTES]>);

struct Pool {
    blocks: [Block; BLOCKS],
    used: [AtomicBool; BLOCKS],
    hint: AtomicUsize,
}

// SAFETY: a block is handed to one owner at a time through the `used` flags.
unsafe impl Sync for Pool {}

#[allow(clippy::declare_interior_mutable_const)]
const FREE_BLOCK: Block = Block(UnsafeCell::new([0; BLOCK_BYTES]));
#[allow(clippy::declare_interior_mutable_const)]
const FREE_FLAG: AtomicBool = AtomicBool::new(false);

static POOL: Pool = Pool { blocks: [FREE_BLOCK; BLOCKS], used: [FREE_FLAG; BLOCKS], hint: AtomicUsize::new(0) };
static SYSTEM_IN_TICK: AtomicU64 = AtomicU64::new(0);
static FREES_IN_TICK: AtomicU64 = AtomicU64::new(0);
static POOL_IN_TICK: AtomicU64 = AtomicU64::new(0);
/// Set by the first allocation through [`CountingAlloc`]: the counts above mean something.
static ACTIVE: AtomicBool = AtomicBool::new(false);
/// Debugging aid (R2G_ABORT_ON_TICK_ALLOC=1 in r2g-control): abort at the offending allocation
/// so a debugger shows where it came from.
pub static ABORT_ON_SYSTEM_ALLOC: AtomicBool = AtomicBool::new(false);

thread_local! {
    static IN_TICK: Cell<bool> = const { Cell::new(false) };
}

fn in_tick() -> bool {
    // try_with: the thread-local may already be gone while a thread shuts down.
    IN_TICK.try_with(Cell::get).unwrap_or(false)
}

impl Pool {
    fn take(&self) -> Option<*mut u8> {
        let start = self.hint.load(Ordering::Relaxed);
        for k in 0..BLOCKS {
            let i = (start + k) % BLOCKS;
            if self.used[i].compare_exchange(false, true, Ordering::Acquire, Ordering::Relaxed).is_ok() {
                self.hint.store((i + 1) % BLOCKS, Ordering::Relaxed);
                return Some(self.blocks[i].0.get().cast());
            }
        }
        None
    }

    fn index_of(&self, p: *mut u8) -> Option<usize> {
        let base = self.blocks.as_ptr() as usize;
        let a = p as usize;
        (a >= base && a < base + BLOCKS * core::mem::size_of::<Block>())
            .then(|| (a - base) / core::mem::size_of::<Block>())
    }
}

/// The system allocator, except for small requests made inside a tick (see the module docs).
pub struct CountingAlloc;

// SAFETY: pool blocks are disjoint, suitably aligned, and owned exclusively between take and
// release; everything else is forwarded to the system allocator unchanged.
unsafe impl GlobalAlloc for CountingAlloc {
    unsafe fn alloc(&self, layout: Layout) -> *mut u8 {
        if !ACTIVE.load(Ordering::Relaxed) {
            ACTIVE.store(true, Ordering::Relaxed);
        }
        if in_tick() {
            if layout.size() <= BLOCK_BYTES && layout.align() <= BLOCK_ALIGN {
                if let Some(p) = POOL.take() {
                    POOL_IN_TICK.fetch_add(1, Ordering::Relaxed);
                    return p;
                }
            }
            SYSTEM_IN_TICK.fetch_add(1, Ordering::Relaxed);
            if ABORT_ON_SYSTEM_ALLOC.load(Ordering::Relaxed) {
                IN_TICK.with(|t| t.set(false));
                eprintln!("allocation of {layout:?} inside a tick:\n{}", std::backtrace::Backtrace::force_capture());
                std::process::abort();
            }
        }
        // SAFETY: same contract as our caller's.
        unsafe { System.alloc(layout) }
    }

    unsafe fn dealloc(&self, ptr: *mut u8, layout: Layout) {
        if let Some(i) = POOL.index_of(ptr) {
            POOL.used[i].store(false, Ordering::Release);
            return;
        }
        if in_tick() {
            // Counted apart: iceoryx2 drops a dead peer's connection (a few bytes) inside the
            // receive or send that first notices the peer is gone, when its cleanup lands
            // between the pre-tick connection update and the tick.
            FREES_IN_TICK.fetch_add(1, Ordering::Relaxed);
        }
        // SAFETY: ptr came from System with this layout.
        unsafe { System.dealloc(ptr, layout) }
    }

    unsafe fn realloc(&self, ptr: *mut u8, layout: Layout, new_size: usize) -> *mut u8 {
        if POOL.index_of(ptr).is_some() || in_tick() {
            // SAFETY: new_size is non-zero per the GlobalAlloc contract and align is unchanged.
            let new_layout = unsafe { Layout::from_size_align_unchecked(new_size, layout.align()) };
            // SAFETY: plain alloc/copy/free through ourselves keeps pool bookkeeping right.
            unsafe {
                let new = self.alloc(new_layout);
                if !new.is_null() {
                    core::ptr::copy_nonoverlapping(ptr, new, layout.size().min(new_size));
                    self.dealloc(ptr, layout);
                }
                return new;
            }
        }
        // SAFETY: same contract as our caller's.
        unsafe { System.realloc(ptr, layout, new_size) }
    }
}

/// Marks the current thread as inside a tick until dropped.
pub struct TickScope;

impl TickScope {
    #[inline]
    pub fn enter() -> Self {
        IN_TICK.with(|t| t.set(true));
        TickScope
    }
}

impl Drop for TickScope {
    #[inline]
    fn drop(&mut self) {
        IN_TICK.with(|t| t.set(false));
    }
}

/// Whether this process allocates through [`CountingAlloc`] (else the counts stay 0).
pub fn counting_active() -> bool {
    ACTIVE.load(Ordering::Relaxed)
}

/// Calls that reached the system allocator from inside a tick (must stay 0).
pub fn tick_allocations() -> u64 {
    SYSTEM_IN_TICK.load(Ordering::Relaxed)
}

/// Frees of system memory inside ticks (see `CountingAlloc::dealloc`).
pub fn tick_frees() -> u64 {
    FREES_IN_TICK.load(Ordering::Relaxed)
}

/// Small allocations inside ticks served by the preallocated pool (iceoryx2's per-loan handle).
pub fn tick_pool_allocations() -> u64 {
    POOL_IN_TICK.load(Ordering::Relaxed)
}
