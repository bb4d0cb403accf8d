//! The kernel-side confinement of a worker, applied by `r2g-sandbox` to itself just before it
//! executes the worker's Python: resource limits, a pids cgroup, no capabilities, no new
//! privileges, landlock (file access, TCP, abstract sockets, signals) and seccomp.
//!
//! Order matters: the cgroup is joined while /sys is still writable, capabilities go before
//! landlock (which forbids nothing about them), and seccomp comes last because its filter also
//! stops `setsid`, `socket` and friends that nothing after it needs.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use anyhow::{bail, Context};
use landlock::{
    path_beneath_rules, Access, AccessFs, AccessNet, CompatLevel, Compatible, LandlockStatus, Ruleset, RulesetAttr,
    RulesetCreatedAttr, RulesetStatus, Scope, ABI,
};
use seccompiler::{
    BpfProgram, SeccompAction, SeccompCmpArgLen, SeccompCmpOp, SeccompCondition, SeccompFilter, SeccompRule, TargetArch,
};
use serde::{Deserialize, Serialize};

/// What the worker may touch, and how much of the machine it may use.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct Policy {
    /// The only place the worker may write (and create files in).
    pub scratch: PathBuf,
    /// Read-only trees (files and folders beneath).
    pub read: Vec<PathBuf>,
    /// Trees whose files may also be executed (the interpreter and the dynamic loader).
    pub exec: Vec<PathBuf>,
    pub cpu_s: u64,
    pub mem_mb: u64,
    pub fsize_mb: u64,
    pub nofile: u64,
    /// A pids cgroup (v1 or v2 folder) to join; the host created it with its `pids.max`.
    pub cgroup: Option<PathBuf>,
}

/// What the kernel actually enforced, reported back to the host.
#[derive(Debug, Clone, Default, Serialize, Deserialize, PartialEq)]
pub struct Enforced {
    /// "full", "partial" or "none".
    pub landlock: String,
    pub landlock_abi: Option<i32>,
    pub seccomp: bool,
    pub no_new_privs: bool,
    pub capabilities_dropped: bool,
    pub cgroup: bool,
    pub warnings: Vec<String>,
}

/// The landlock ABI we ask for. Pinned: a newer ABI handles rights (e.g. connecting to Unix
/// sockets by path) that this policy does not grant, so taking "all" would deny them silently.
const LANDLOCK_ABI: ABI = ABI::V7;

fn set_rlimit(resource: libc::__rlimit_resource_t, soft: u64, hard: u64) -> anyhow::Result<()> {
    let lim = libc::rlimit { rlim_cur: soft, rlim_max: hard };
    // SAFETY: setrlimit reads the struct we pass.
    if unsafe { libc::setrlimit(resource, &lim) } != 0 {
        bail!("setrlimit({resource}): {}", std::io::Error::last_os_error());
    }
    Ok(())
}

fn limits(p: &Policy) -> anyhow::Result<()> {
    set_rlimit(libc::RLIMIT_CPU, p.cpu_s, p.cpu_s + 1)?;
    let mem = p.mem_mb << 20;
    set_rlimit(libc::RLIMIT_AS, mem, mem)?;
    let fsize = p.fsize_mb << 20;
    set_rlimit(libc::RLIMIT_FSIZE, fsize, fsize)?;
    set_rlimit(libc::RLIMIT_NOFILE, p.nofile, p.nofile)?;
    set_rlimit(libc::RLIMIT_CORE, 0, 0)?;
    // Counts per user, and not for root; the pids cgroup and seccomp are what hold for root.
    set_rlimit(libc::RLIMIT_NPROC, 64, 64)?;
    Ok(())
}

fn join_cgroup(dir: &Path) -> anyhow::Result<()> {
    let pid = std::process::id().to_string();
    std::fs::write(dir.join("cgroup.procs"), pid).with_context(|| format!("joining cgroup {}", dir.display()))
}

#[repr(C)]
struct CapHeader {
    version: u32,
    pid: i32,
}

#[repr(C)]
#[derive(Clone, Copy)]
struct CapData {
    effective: u32,
    permitted: u32,
    inheritable: u32,
}

/// Empties the bounding set (so executing the interpreter grants nothing back, even to root)
/// and the current capability sets.
fn drop_capabilities() -> anyhow::Result<()> {
    for cap in 0..64 {
        // SAFETY: plain prctl; EINVAL past the last capability is expected and ignored.
        unsafe { libc::prctl(libc::PR_CAPBSET_DROP, cap, 0, 0, 0) };
    }
    // SAFETY: PR_CAP_AMBIENT_CLEAR_ALL takes no pointers.
    unsafe { libc::prctl(libc::PR_CAP_AMBIENT, libc::PR_CAP_AMBIENT_CLEAR_ALL, 0, 0, 0) };
    let header = CapHeader { version: 0x2008_0522, pid: 0 };
    let data = [CapData { effective: 0, permitted: 0, inheritable: 0 }; 2];
    // SAFETY: capset reads a v3 header and two data structs.
    if unsafe { libc::syscall(libc::SYS_capset, &header, data.as_ptr()) } != 0 {
        bail!("capset: {}", std::io::Error::last_os_error());
    }
    Ok(())
}

fn existing(paths: &[PathBuf]) -> Vec<&Path> {
    paths.iter().map(PathBuf::as_path).filter(|p| p.exists()).collect()
}

fn landlock(p: &Policy, out: &mut Enforced) -> anyhow::Result<()> {
    let abi = LANDLOCK_ABI;
    let read = AccessFs::from_read(abi) & !AccessFs::Execute;
    let status = Ruleset::default()
        .set_compatibility(CompatLevel::BestEffort)
        .handle_access(AccessFs::from_all(abi))?
        .handle_access(AccessNet::from_all(abi))?
        .scope(Scope::from_all(abi))?
        .create()?
        .add_rules(path_beneath_rules(existing(&p.read), read))?
        .add_rules(path_beneath_rules(existing(&p.exec), AccessFs::from_read(abi)))?
        .add_rules(path_beneath_rules([p.scratch.as_path()], AccessFs::from_all(abi) & !AccessFs::Execute))?
        .add_rules(path_beneath_rules(
            [Path::new("/dev/null")],
            AccessFs::ReadFile | AccessFs::WriteFile | AccessFs::Truncate,
        ))?
        .restrict_self()
        .context("landlock")?;
    out.landlock = match status.ruleset {
        RulesetStatus::FullyEnforced => "full",
        RulesetStatus::PartiallyEnforced => "partial",
        RulesetStatus::NotEnforced => "none",
    }
    .into();
    out.landlock_abi = match status.landlock {
        LandlockStatus::Available { effective_abi, .. } => Some(effective_abi as i32),
        _ => None,
    };
    out.no_new_privs = status.no_new_privs;
    if out.landlock != "full" {
        out.warnings.push(format!(
            "landlock is only {}-enforced on this kernel: file, network and signal isolation is weaker",
            out.landlock
        ));
    }
    Ok(())
}

/// Syscalls a stage program never needs; any use kills the worker (reported as a violation).
const FORBIDDEN: &[i64] = &[
    libc::SYS_socket,
    libc::SYS_socketpair,
    libc::SYS_ptrace,
    libc::SYS_process_vm_readv,
    libc::SYS_process_vm_writev,
    libc::SYS_kexec_load,
    libc::SYS_kexec_file_load,
    libc::SYS_mount,
    libc::SYS_umount2,
    libc::SYS_pivot_root,
    libc::SYS_chroot,
    libc::SYS_fsopen,
    libc::SYS_fsconfig,
    libc::SYS_fsmount,
    libc::SYS_fspick,
    libc::SYS_move_mount,
    libc::SYS_open_tree,
    libc::SYS_mount_setattr,
    libc::SYS_bpf,
    libc::SYS_perf_event_open,
    libc::SYS_keyctl,
    libc::SYS_add_key,
    libc::SYS_request_key,
    libc::SYS_unshare,
    libc::SYS_setns,
    libc::SYS_personality,
    libc::SYS_userfaultfd,
    libc::SYS_io_uring_setup,
    libc::SYS_io_uring_enter,
    libc::SYS_io_uring_register,
    libc::SYS_init_module,
    libc::SYS_finit_module,
    libc::SYS_delete_module,
    libc::SYS_swapon,
    libc::SYS_swapoff,
    libc::SYS_reboot,
    libc::SYS_open_by_handle_at,
    libc::SYS_name_to_handle_at,
    libc::SYS_iopl,
    libc::SYS_ioperm,
    libc::SYS_memfd_create,
    libc::SYS_execveat,
    libc::SYS_setsid,
    libc::SYS_setpgid,
    libc::SYS_fork,
    libc::SYS_vfork,
    libc::SYS_acct,
    libc::SYS_settimeofday,
    libc::SYS_clock_settime,
    libc::SYS_quotactl,
    // System V IPC outlives the worker and escapes its limits.
    libc::SYS_shmget,
    libc::SYS_shmat,
    libc::SYS_shmdt,
    libc::SYS_shmctl,
    libc::SYS_msgget,
    libc::SYS_msgsnd,
    libc::SYS_msgrcv,
    libc::SYS_msgctl,
    libc::SYS_semget,
    libc::SYS_semop,
    libc::SYS_semtimedop,
    libc::SYS_semctl,
    libc::SYS_mq_open,
    libc::SYS_mq_unlink,
];

/// Syscalls that change file metadata; refused with EPERM.
const METADATA: &[i64] = &[
    libc::SYS_chmod,
    libc::SYS_fchmod,
    libc::SYS_fchmodat,
    libc::SYS_chown,
    libc::SYS_fchown,
    libc::SYS_lchown,
    libc::SYS_fchownat,
    libc::SYS_utime,
    libc::SYS_utimes,
    libc::SYS_utimensat,
    libc::SYS_futimesat,
    libc::SYS_setxattr,
    libc::SYS_lsetxattr,
    libc::SYS_fsetxattr,
    libc::SYS_removexattr,
    libc::SYS_lremovexattr,
    libc::SYS_fremovexattr,
];

fn seccomp(out: &mut Enforced) -> anyhow::Result<()> {
    let mut rules: BTreeMap<i64, Vec<SeccompRule>> = FORBIDDEN.iter().map(|&s| (s, Vec::new())).collect();
    // clone: threads only (CLONE_THREAD set); a new process is a violation.
    let no_thread =
        SeccompCondition::new(0, SeccompCmpArgLen::Qword, SeccompCmpOp::MaskedEq(libc::CLONE_THREAD as u64), 0)?;
    rules.insert(libc::SYS_clone, vec![SeccompRule::new(vec![no_thread])?]);
    // Typing into the controlling terminal.
    let tiocsti = SeccompCondition::new(1, SeccompCmpArgLen::Dword, SeccompCmpOp::Eq, libc::TIOCSTI)?;
    rules.insert(libc::SYS_ioctl, vec![SeccompRule::new(vec![tiocsti])?]);
    let kill: BpfProgram =
        SeccompFilter::new(rules, SeccompAction::Allow, SeccompAction::KillProcess, TargetArch::x86_64)?.try_into()?;
    // clone3 hides its flags in memory the filter cannot read: ENOSYS makes the C library fall
    // back to clone, which the filter above can judge.
    let clone3: BpfProgram = SeccompFilter::new(
        BTreeMap::from([(libc::SYS_clone3, Vec::new())]),
        SeccompAction::Allow,
        SeccompAction::Errno(libc::ENOSYS as u32),
        TargetArch::x86_64,
    )?
    .try_into()?;
    // File metadata (modes, owners, times, extended attributes) is outside landlock's reach:
    // refused, so a program cannot alter files it may only read.
    let metadata: BpfProgram = SeccompFilter::new(
        METADATA.iter().map(|&s| (s, Vec::new())).collect(),
        SeccompAction::Allow,
        SeccompAction::Errno(libc::EPERM as u32),
        TargetArch::x86_64,
    )?
    .try_into()?;
    // Calls that act on another process by pid (limits, scheduling, priorities, memory
    // placement) are refused unless they name the caller itself (pid 0): landlock scopes
    // signals and ptrace, not these.
    let other = |arg: u8| SeccompCondition::new(arg, SeccompCmpArgLen::Dword, SeccompCmpOp::Ne, 0);
    let mut by_pid: BTreeMap<i64, Vec<SeccompRule>> = BTreeMap::new();
    for (sys, arg) in [
        (libc::SYS_prlimit64, 0),
        (libc::SYS_sched_setaffinity, 0),
        (libc::SYS_sched_setscheduler, 0),
        (libc::SYS_sched_setparam, 0),
        (libc::SYS_sched_setattr, 0),
        (libc::SYS_migrate_pages, 0),
        (libc::SYS_move_pages, 0),
        (libc::SYS_setpriority, 1),
        (libc::SYS_ioprio_set, 1),
    ] {
        by_pid.insert(sys, vec![SeccompRule::new(vec![other(arg)?])?]);
    }
    // Priorities of a whole process group or user (which includes the host) are refused too.
    for (sys, kind) in
        [(libc::SYS_setpriority, 0u64 /* PRIO_PROCESS */), (libc::SYS_ioprio_set, 1 /* IOPRIO_WHO_PROCESS */)]
    {
        let other_kind = SeccompCondition::new(0, SeccompCmpArgLen::Dword, SeccompCmpOp::Ne, kind)?;
        by_pid.entry(sys).or_default().push(SeccompRule::new(vec![other_kind])?);
    }
    by_pid.insert(libc::SYS_kcmp, Vec::new());
    let by_pid: BpfProgram =
        SeccompFilter::new(by_pid, SeccompAction::Allow, SeccompAction::Errno(libc::EPERM as u32), TargetArch::x86_64)?
            .try_into()?;
    seccompiler::apply_filter(&by_pid).context("seccomp (other processes)")?;
    seccompiler::apply_filter(&clone3).context("seccomp (clone3)")?;
    seccompiler::apply_filter(&metadata).context("seccomp (metadata)")?;
    seccompiler::apply_filter(&kill).context("seccomp")?;
    out.seccomp = true;
    Ok(())
}

/// Confines the calling process. Returns what was enforced; fails when a mandatory layer
/// (limits, capabilities, seccomp, landlock itself) cannot be applied at all.
pub fn confine(p: &Policy) -> anyhow::Result<Enforced> {
    let mut out = Enforced::default();
    limits(p)?;
    // SAFETY: plain prctl with integer arguments.
    unsafe { libc::prctl(libc::PR_SET_PDEATHSIG, libc::SIGKILL, 0, 0, 0) };
    if let Some(dir) = &p.cgroup {
        match join_cgroup(dir) {
            Ok(()) => out.cgroup = true,
            Err(e) => out.warnings.push(format!("{e:#}: only the address-space limit bounds threads")),
        }
    }
    drop_capabilities()?;
    out.capabilities_dropped = true;
    landlock(p, &mut out)?;
    seccomp(&mut out)?;
    Ok(out)
}
