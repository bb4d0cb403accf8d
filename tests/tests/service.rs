//! `r2g service install` (deploy/): the units it writes pass the real `systemd-analyze verify`
//! without a warning, the control unit's sandbox scores at most 3.0 in `systemd-analyze security
//! --offline=yes` (a real arm's robot side, r2g-fci@, at most 2.0), an instance with `--fci`
//! has r2g-fci@ as its robot side in place of r2g-sim@ and reaches the arm's address only, the users, folders and iceoryx2 configurations it ships are what the real
//! systemd-sysusers, systemd-tmpfiles and iceoryx2 make of them, the agent unit and its user
//! stay out of the control instance's folders (iceoryx2's segments there are writable by whoever
//! enters them), and bad input is refused with the key and what is accepted, writing nothing.
//! systemd need not run here (it is not PID 1 in CI); these commands work offline.

use std::path::{Path, PathBuf};
use std::process::{Command, Output};

use integration_tests::r2g;

const GYM: &str = "pick_block_plate";

/// A folder under the system temp dir, removed on drop (also when the test fails).
struct Temp(PathBuf);

impl Temp {
    fn new(tag: &str) -> Self {
        let p = std::env::temp_dir().join(format!("r2g-service-{}-{tag}", std::process::id()));
        let _ = std::fs::remove_dir_all(&p);
        std::fs::create_dir_all(&p).expect("temp dir");
        Self(p)
    }
}

impl Drop for Temp {
    fn drop(&mut self) {
        let _ = std::fs::remove_dir_all(&self.0);
    }
}

fn tool(name: &str) -> PathBuf {
    for dir in std::env::var("PATH").unwrap_or_default().split(':').chain(["/usr/bin", "/bin"]) {
        let p = Path::new(dir).join(name);
        if p.is_file() {
            return p;
        }
    }
    panic!("{name} not found: install the Debian systemd package (scripts/install-deps.sh does)");
}

fn run(cmd: &mut Command) -> Output {
    let out = cmd.output().unwrap_or_else(|e| panic!("running {cmd:?}: {e}"));
    eprintln!("$ {cmd:?}\n{}{}", String::from_utf8_lossy(&out.stdout), String::from_utf8_lossy(&out.stderr));
    out
}

fn install(root: &Path, args: &[&str]) -> Output {
    run(Command::new(r2g()).args(["service", "install"]).args(args).arg("--root").arg(root))
}

fn installed(tag: &str, args: &[&str]) -> (Temp, String) {
    let root = Temp::new(tag);
    let name = integration_tests::instance(tag);
    let mut all = vec![GYM, "--instance", &name];
    all.extend_from_slice(args);
    let out = install(&root.0, &all);
    assert!(out.status.success(), "install failed: {}", String::from_utf8_lossy(&out.stderr));
    (root, name)
}

fn units(name: &str) -> [String; 4] {
    [
        format!("r2g-control@{name}.service"),
        format!("r2g-sim@{name}.service"),
        format!("r2g-agent@{name}.service"),
        format!("r2g@{name}.target"),
    ]
}

#[test]
fn every_installed_unit_verifies_without_a_warning() {
    let (root, name) = installed("verify", &[]);
    let dir = root.0.join("etc/systemd/system");
    for unit in units(&name) {
        // An instance path next to its template: verify loads the template and the instance's
        // drop-ins (r2g-control@NAME.service.d/).
        let out = run(Command::new(tool("systemd-analyze")).arg("verify").arg(dir.join(&unit)));
        assert!(out.status.success(), "systemd-analyze verify {unit} failed");
        let stderr = String::from_utf8_lossy(&out.stderr);
        assert!(stderr.trim().is_empty(), "systemd-analyze verify {unit} warned:\n{stderr}");
    }
    // The drop-ins were read: a bad one is reported (so the clean run above covered them).
    let drop_in = dir.join(format!("r2g-control@{name}.service.d/20-probe.conf"));
    std::fs::write(&drop_in, "[Service]\nNoSuchSetting=1\n").expect("probe drop-in");
    let out = run(Command::new(tool("systemd-analyze")).arg("verify").arg(dir.join(&units(&name)[0])));
    assert!(String::from_utf8_lossy(&out.stderr).contains("NoSuchSetting"), "verify did not read the drop-ins");
}

#[test]
fn the_shipped_templates_verify_as_they_are() {
    // What a packager or reviewer runs on the checkout's own files, before any install.
    let dir = integration_tests::root().join("deploy/systemd");
    for unit in ["r2g@.target", "r2g-control@.service", "r2g-sim@.service", "r2g-fci@.service", "r2g-agent@.service"] {
        let out = run(Command::new(tool("systemd-analyze")).arg("verify").arg(dir.join(unit)));
        let stderr = String::from_utf8_lossy(&out.stderr);
        assert!(
            out.status.success() && stderr.trim().is_empty(),
            "systemd-analyze verify deploy/systemd/{unit}:\n{stderr}"
        );
    }
}

/// "→ Overall exposure level for r2g-control@x.service: 0.6 SAFE 😀" → 0.6
fn exposure(text: &str) -> Option<f64> {
    let line = text.lines().find(|l| l.contains("Overall exposure level"))?;
    line.rsplit(':').next()?.split_whitespace().next()?.parse().ok()
}

/// `systemd-analyze security --offline=yes` of an installed unit: its overall exposure, printed.
fn security(dir: &Path, unit: &str) -> f64 {
    let out = run(Command::new(tool("systemd-analyze"))
        .args(["security", "--offline=yes", "--no-pager"])
        .arg(dir.join(unit)));
    assert!(out.status.success(), "systemd-analyze security {unit} failed");
    let text = String::from_utf8_lossy(&out.stdout);
    let score = exposure(&text).unwrap_or_else(|| panic!("no overall exposure for {unit}:\n{text}"));
    println!("systemd-analyze security --offline=yes {unit}: exposure {score}");
    score
}

#[test]
fn the_control_unit_exposure_is_at_most_3() {
    let (root, name) = installed("security", &[]);
    let dir = root.0.join("etc/systemd/system");
    // The target runs no process: only services have a sandbox to score.
    let scores: Vec<f64> = units(&name)[..3].iter().map(|unit| security(&dir, unit)).collect();
    assert!(scores[0] <= 3.0, "control unit exposure {} > 3.0", scores[0]);
}

/// The root path of an iceoryx2 configuration file, as iceoryx2's own loader reads it.
fn iceoryx2_root(cfg_path: &Path) -> String {
    use iceoryx2::prelude::SemanticString;
    let file = iceoryx2::prelude::FilePath::new(cfg_path.to_str().expect("utf-8").as_bytes()).expect("file path");
    let cfg = iceoryx2::config::Config::from_file(&file)
        .unwrap_or_else(|e| panic!("iceoryx2 cannot load {}: {e:?}", cfg_path.display()));
    cfg.global.root_path().to_string()
}

/// Whether a process of `uid`/`gid` (no supplementary groups) may enter `dir` and create files
/// in it: `test -x && test -w` (access(2)) after dropping to those ids. Needs root.
fn may_write_into(uid: u32, gid: u32, dir: &Path) -> bool {
    use std::os::unix::process::CommandExt;
    let mut cmd = Command::new("/bin/sh");
    cmd.args(["-c", "test -x \"$1\" && test -w \"$1\"", "sh"]).arg(dir);
    // SAFETY: only async-signal-safe calls between fork and exec.
    unsafe {
        cmd.pre_exec(move || {
            if libc::setgroups(0, std::ptr::null()) != 0 || libc::setgid(gid) != 0 || libc::setuid(uid) != 0 {
                return Err(std::io::Error::last_os_error());
            }
            Ok(())
        });
    }
    cmd.status().unwrap_or_else(|e| panic!("test -w {} as uid {uid}: {e}", dir.display())).success()
}

#[test]
fn users_folders_and_iceoryx2_root_are_what_the_real_tools_make_of_them() {
    let (root, name) = installed("files", &[]);
    let r = &root.0;
    // systemd-sysusers creates the users and groups in the root's own /etc/passwd and /etc/group.
    let out = run(Command::new(tool("systemd-sysusers"))
        .arg(format!("--root={}", r.display()))
        .arg(r.join("etc/sysusers.d/r2g.conf")));
    assert!(out.status.success(), "systemd-sysusers failed");
    let passwd = std::fs::read_to_string(r.join("etc/passwd")).expect("passwd");
    let group = std::fs::read_to_string(r.join("etc/group")).expect("group");
    let field = |db: &str, n: &str, i: usize| -> u32 {
        let line = db.lines().find(|l| l.split(':').next() == Some(n)).unwrap_or_else(|| panic!("no {n}:\n{db}"));
        line.split(':').nth(i).and_then(|v| v.parse().ok()).expect("numeric id")
    };
    let (r2g_uid, r2g_gid) = (field(&passwd, "r2g", 2), field(&group, "r2g", 2));
    let (agent_uid, agent_gid) = (field(&passwd, "r2g-agent", 2), field(&group, "r2g-agent", 2));
    assert_ne!(r2g_uid, agent_uid, "control and agent must be different users");
    assert_ne!(r2g_gid, agent_gid, "the agent must have a group of its own");
    assert_eq!(field(&passwd, "r2g", 3), r2g_gid, "r2g's primary group");
    assert_eq!(field(&passwd, "r2g-agent", 3), agent_gid, "r2g-agent's primary group must be r2g-agent");
    let _ = field(&group, "r2g-operator", 2);
    // Group r2g (the control instance's folders) lists no members (user r2g has it as its primary
    // group), and r2g-agent is listed in no group at all.
    let r2g_line = group.lines().find(|l| l.starts_with("r2g:")).expect("group r2g");
    assert!(r2g_line.ends_with(':'), "group r2g must have no members: {r2g_line}");
    for line in group.lines() {
        let members = line.split(':').nth(3).unwrap_or("");
        assert!(!members.split(',').any(|m| m == "r2g-agent"), "r2g-agent must be in no group: {line}");
    }

    // The iceoryx2 configurations move the root paths under the instance's run folder: the
    // control instance's, and the agent unit's own.
    assert_eq!(iceoryx2_root(&r.join(format!("etc/r2g/{name}/iceoryx2.toml"))), format!("/run/r2g/{name}/iceoryx2/"));
    assert_eq!(
        iceoryx2_root(&r.join(format!("etc/r2g/{name}/agent-iceoryx2.toml"))),
        format!("/run/r2g/{name}/agent/iceoryx2/")
    );

    // systemd-tmpfiles creates the instance's folders with the users above (chown needs root).
    // SAFETY: geteuid cannot fail.
    if unsafe { libc::geteuid() } != 0 {
        println!("not root: systemd-tmpfiles --create (which chowns) is not run");
        return;
    }
    let out = run(Command::new(tool("systemd-tmpfiles"))
        .arg(format!("--root={}", r.display()))
        .arg("--create")
        .arg(r.join(format!("etc/tmpfiles.d/r2g-{name}.conf"))));
    assert!(out.status.success(), "systemd-tmpfiles failed");
    // tmpfiles refuses to work below a folder of one unprivileged user that holds another
    // user's ("unsafe path transition"): nothing may be reported, and every folder must be there.
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(stderr.trim().is_empty(), "systemd-tmpfiles warned:\n{stderr}");
    use std::os::unix::fs::MetadataExt;
    let folders = [
        ("", 0o771, 0, r2g_gid),
        ("/iceoryx2", 0o2770, r2g_uid, r2g_gid),
        ("/shm", 0o2770, r2g_uid, r2g_gid),
        ("/agent", 0o750, agent_uid, agent_gid),
        ("/agent/iceoryx2", 0o2770, agent_uid, agent_gid),
        ("/agent/shm", 0o2770, agent_uid, agent_gid),
        ("/agent/run", 0o750, agent_uid, agent_gid),
    ];
    for (sub, mode, uid, gid) in folders {
        let p = r.join(format!("run/r2g/{name}{sub}"));
        let m = std::fs::metadata(&p).unwrap_or_else(|e| panic!("{}: {e}", p.display()));
        assert_eq!(m.mode() & 0o7777, mode, "{} mode {:o}", p.display(), m.mode() & 0o7777);
        assert_eq!((m.uid(), m.gid()), (uid, gid), "{} owner", p.display());
    }

    // What each user may do there, asked of the kernel as that user (its groups as above): only
    // r2g writes into the control instance's folders, only r2g-agent into the agent's.
    use std::os::unix::fs::PermissionsExt;
    std::fs::set_permissions(r, std::fs::Permissions::from_mode(0o755)).expect("chmod the temp root");
    let run_dir = r.join(format!("run/r2g/{name}"));
    for (sub, control, agent) in [
        ("", true, false),
        ("iceoryx2", true, false),
        ("shm", true, false),
        ("agent/iceoryx2", false, true),
        ("agent/shm", false, true),
        ("agent/run", false, true),
    ] {
        let p = run_dir.join(sub);
        assert_eq!(may_write_into(r2g_uid, r2g_gid, &p), control, "user r2g writing into {}", p.display());
        assert_eq!(may_write_into(agent_uid, agent_gid, &p), agent, "user r2g-agent writing into {}", p.display());
    }
}

/// The directives of an installed unit: its template (`r2g-sim@.service`, `r2g@.target`) and
/// its drop-ins in order, `%i` replaced, comments left out, as `(key, value)`.
fn directives(dir: &Path, template: &str, name: &str) -> Vec<(String, String)> {
    let mut files = vec![dir.join(template)];
    let drop_ins = dir.join(format!("{}.d", template.replacen("@.", &format!("@{name}."), 1)));
    let mut extra: Vec<PathBuf> =
        std::fs::read_dir(&drop_ins).into_iter().flatten().flatten().map(|e| e.path()).collect();
    extra.sort();
    files.extend(extra);
    let mut out = Vec::new();
    for f in files {
        let text = std::fs::read_to_string(&f).unwrap_or_else(|e| panic!("{}: {e}", f.display()));
        for line in text.lines().map(str::trim).filter(|l| !l.starts_with('#') && !l.starts_with(';')) {
            if let Some((k, v)) = line.split_once('=') {
                out.push((k.trim().to_string(), v.trim().replace("%i", name)));
            }
        }
    }
    out
}

/// The words of every `key=` line, quotes left out.
fn values<'a>(d: &'a [(String, String)], key: &str) -> Vec<&'a str> {
    d.iter().filter(|(k, _)| k == key).flat_map(|(_, v)| v.split_whitespace()).map(|w| w.trim_matches('"')).collect()
}

#[test]
fn the_agent_unit_has_folders_of_its_own() {
    let (root, name) = installed("agentdirs", &[]);
    let dir = root.0.join("etc/systemd/system");
    let control_shm = format!("/run/r2g/{name}/shm");
    let control_ipc = format!("/run/r2g/{name}/iceoryx2");
    let control_cfg = format!("/etc/r2g/{name}/iceoryx2.toml");

    // The control process and the robot side share the instance's folders, as user r2g.
    for unit in ["r2g-control@.service", "r2g-sim@.service"] {
        let d = directives(&dir, unit, &name);
        assert_eq!(values(&d, "User"), ["r2g"], "{unit}");
        assert_eq!(values(&d, "Group"), ["r2g"], "{unit}");
        assert_eq!(values(&d, "BindPaths"), [format!("{control_shm}:/dev/shm")], "{unit}");
        assert!(values(&d, "Environment").contains(&format!("R2G_IPC_CONFIG={control_cfg}").as_str()), "{unit}");
    }

    // The agent unit: its own user and group, /dev/shm, iceoryx2 root and run folder.
    let d = directives(&dir, "r2g-agent@.service", &name);
    assert_eq!(values(&d, "User"), ["r2g-agent"]);
    assert_eq!(values(&d, "Group"), ["r2g-agent"]);
    assert_eq!(values(&d, "BindPaths"), [format!("/run/r2g/{name}/agent/shm:/dev/shm")]);
    let env = values(&d, "Environment");
    let agent_cfg = format!("/etc/r2g/{name}/agent-iceoryx2.toml");
    for want in [format!("R2G_IPC_CONFIG={agent_cfg}"), format!("R2G_RUN_DIR=/run/r2g/{name}/agent/run")] {
        assert!(env.contains(&want.as_str()), "the agent unit lacks {want}: {env:?}");
    }
    assert_eq!(env.iter().filter(|v| v.starts_with("R2G_IPC_CONFIG=")).count(), 1, "{env:?}");
    assert_eq!(env.iter().filter(|v| v.starts_with("R2G_RUN_DIR=")).count(), 1, "{env:?}");
    let writable = values(&d, "ReadWritePaths");
    assert!(!writable.is_empty(), "the agent unit has no ReadWritePaths=");
    for p in &writable {
        let p = p.trim_start_matches(['-', '+']);
        assert!(p == format!("/run/r2g/{name}/agent") || p.starts_with(&format!("/run/r2g/{name}/agent/")), "{p}");
    }
    // The control instance's folders are hidden from it, and named nowhere else in the unit.
    let hidden: Vec<&str> = values(&d, "InaccessiblePaths").iter().map(|p| p.trim_start_matches('-')).collect();
    for p in [&control_shm, &control_ipc] {
        assert!(hidden.contains(&p.as_str()), "the agent unit does not hide {p}: {hidden:?}");
    }
    for (k, v) in d.iter().filter(|(k, _)| k != "InaccessiblePaths") {
        for p in [&control_shm, &control_ipc, &control_cfg] {
            let named = v.split([' ', '=', ':', '"', '\'']).any(|t| t == p.as_str() || t == format!("{p}/"));
            assert!(!named, "the agent unit's {k}={v} names the control instance's {p}");
        }
    }
    // Its configuration file is installed and points at its own iceoryx2 root.
    assert_eq!(
        iceoryx2_root(&root.0.join(agent_cfg.trim_start_matches('/'))),
        format!("/run/r2g/{name}/agent/iceoryx2/")
    );

    // A machine installed before has r2g-agent in group r2g; sysusers never removes that, so
    // install says how to.
    let again = Temp::new("oldgroup");
    std::fs::create_dir_all(again.0.join("etc")).expect("etc");
    std::fs::write(again.0.join("etc/group"), "r2g:x:990:r2g-agent\nr2g-agent:x:989:\n").expect("group");
    let out = install(&again.0, &[GYM, "--instance", &name]);
    assert!(out.status.success(), "install failed");
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(stderr.contains("gpasswd -d r2g-agent r2g"), "no note on the leftover membership:\n{stderr}");
    let clean = install(&root.0, &[GYM, "--instance", &name]);
    assert!(!String::from_utf8_lossy(&clean.stderr).contains("gpasswd"), "a note without a leftover membership");
}

/// The arm of the fci tests: a franka-profile robot config (what a real arm needs) in `dir`,
/// and the install arguments of an instance driving the arm at `address` with its hand.
fn fci_args(dir: &Path, name: &str, address: &str) -> Vec<String> {
    let robot = dir.join("franka.json");
    std::fs::write(&robot, "{\"profile\": \"franka\"}\n").expect("robot config");
    let robot = robot.to_str().expect("utf-8");
    [robot, "--gym", GYM, "--instance", name, "--fci", address, "--fci-gripper"].map(String::from).to_vec()
}

/// That the target and the control unit want (and start after) `side`, not `other`.
fn robot_side_is(dir: &Path, name: &str, side: &str, other: &str) {
    let (side, other) = (format!("{side}@{name}.service"), format!("{other}@{name}.service"));
    for template in ["r2g@.target", "r2g-control@.service"] {
        let d = directives(dir, template, name);
        for key in ["Wants", "After"] {
            let v = values(&d, key);
            assert!(v.contains(&side.as_str()), "{template} of {name}: {key}= lacks {side}: {v:?}");
            assert!(!v.contains(&other.as_str()), "{template} of {name}: {key}= names {other}: {v:?}");
        }
    }
}

#[test]
fn an_fci_instance_runs_r2g_fci_in_place_of_the_simulator() {
    let root = Temp::new("fci");
    let name = integration_tests::instance("fci");
    let args = fci_args(&root.0, &name, "172.16.0.2:1337");
    let out = install(&root.0.join("root"), &args.iter().map(String::as_str).collect::<Vec<_>>());
    assert!(out.status.success(), "install failed: {}", String::from_utf8_lossy(&out.stderr));
    let dir = root.0.join("root/etc/systemd/system");

    // Every unit of the instance verifies without a word, the fci unit with its drop-in.
    let fci = format!("r2g-fci@{name}.service");
    assert!(dir.join(format!("{fci}.d/10-r2g.conf")).is_file(), "no drop-in for {fci}");
    for unit in [fci.clone(), format!("r2g-control@{name}.service"), format!("r2g@{name}.target")] {
        let out = run(Command::new(tool("systemd-analyze")).arg("verify").arg(dir.join(&unit)));
        let stderr = String::from_utf8_lossy(&out.stderr);
        assert!(out.status.success() && stderr.trim().is_empty(), "systemd-analyze verify {unit}:\n{stderr}");
    }
    assert!(!dir.join(format!("r2g-sim@{name}.service.d")).exists(), "an fci instance got a simulator drop-in");
    robot_side_is(&dir, &name, "r2g-fci", "r2g-sim");

    // The fci unit: the instance's user, shared memory and iceoryx2 root, like the simulator; the
    // arm's address and nothing else on the network; real-time scheduling allowed.
    let d = directives(&dir, "r2g-fci@.service", &name);
    assert_eq!(values(&d, "User"), ["r2g"]);
    assert_eq!(values(&d, "Group"), ["r2g"]);
    assert_eq!(values(&d, "BindPaths"), [format!("/run/r2g/{name}/shm:/dev/shm")]);
    assert_eq!(values(&d, "PartOf"), [format!("r2g@{name}.target"), format!("r2g-control@{name}.service")]);
    let env = values(&d, "Environment");
    for want in [
        format!("R2G_IPC_CONFIG=/etc/r2g/{name}/iceoryx2.toml"),
        "R2G_FCI_ADDRESS=172.16.0.2:1337".into(),
        "R2G_FCI_ARGS=--gripper".into(),
    ] {
        assert!(env.contains(&want.as_str()), "the fci unit lacks {want}: {env:?}");
    }
    assert_eq!(values(&d, "IPAddressDeny"), ["any"]);
    assert_eq!(values(&d, "IPAddressAllow"), ["172.16.0.2"]);
    assert_eq!(values(&d, "RestrictAddressFamilies"), ["AF_UNIX", "AF_INET"]);
    assert!(!values(&d, "PrivateNetwork").contains(&"yes"), "the fci unit has no network");
    assert_eq!(values(&d, "RestrictRealtime"), ["no"]);
    assert_eq!(values(&d, "LimitRTPRIO"), ["99"], "r2g-fci's FCI client asks for SCHED_FIFO priority 99");
    assert_eq!(values(&d, "Restart"), ["on-failure"]);

    // Its sandbox: the simulator's, less PrivateNetwork= and RestrictRealtime=, plus
    // MemoryDenyWriteExecute= (1.4 when written; the control unit's bound is 3.0).
    let score = security(&dir, &fci);
    assert!(score <= 2.0, "r2g-fci@ exposure {score} > 2.0");
}

#[test]
fn reinstalling_keeps_or_switches_the_robot_side() {
    let root = Temp::new("switch");
    let name = integration_tests::instance("switch");
    let args = fci_args(&root.0, &name, "172.16.0.2");
    let r = root.0.join("root");
    let out = install(&r, &args.iter().map(String::as_str).collect::<Vec<_>>());
    assert!(out.status.success(), "install failed");
    let dir = r.join("etc/systemd/system");
    let fci_drop_in = dir.join(format!("r2g-fci@{name}.service.d/10-r2g.conf"));
    let first = std::fs::read_to_string(&fci_drop_in).expect("fci drop-in");

    // instance.toml carries the arm: installing from it alone writes the same fci drop-in.
    let instance_toml = r.join(format!("etc/r2g/{name}/instance.toml"));
    let toml = instance_toml.to_str().expect("utf-8");
    let out = install(&r, &[&args[0], "--gym", GYM, "--instance", &name, "--config", toml]);
    assert!(out.status.success(), "reinstall failed");
    assert_eq!(std::fs::read_to_string(&fci_drop_in).expect("fci drop-in"), first);
    robot_side_is(&dir, &name, "r2g-fci", "r2g-sim");

    // Back to the simulator: its drop-in replaces the fci one, which is removed, with a note.
    let out = install(&r, &[GYM, "--instance", &name]);
    assert!(out.status.success(), "install as a simulator failed");
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(stderr.contains(&format!("stop r2g-fci@{name}.service")), "no note on the old robot side:\n{stderr}");
    assert!(!fci_drop_in.parent().expect("folder").exists(), "the fci drop-in is left");
    assert!(dir.join(format!("r2g-sim@{name}.service.d/10-r2g.conf")).is_file());
    robot_side_is(&dir, &name, "r2g-sim", "r2g-fci");
    let target = dir.join(format!("r2g@{name}.target"));
    let out = run(Command::new(tool("systemd-analyze")).arg("verify").arg(&target));
    assert!(out.status.success() && out.stderr.is_empty(), "systemd-analyze verify {}", target.display());
}

#[test]
fn the_instance_file_installs_the_same_again() {
    let values = Temp::new("values");
    let cfg = values.0.join("lab.toml");
    std::fs::write(&cfg, "# a lab PC\ncpu = 0\nfifo_priority = 70\nrender_hz = 5\ntrace = false\n").expect("config");
    let (root, name) = installed("again", &["--config", cfg.to_str().expect("utf-8")]);
    let control = root.0.join(format!("etc/systemd/system/r2g-control@{name}.service.d/10-r2g.conf"));
    let sim = root.0.join(format!("etc/systemd/system/r2g-sim@{name}.service.d/10-r2g.conf"));
    let read = |p: &Path| std::fs::read_to_string(p).unwrap_or_else(|e| panic!("{}: {e}", p.display()));
    let (c1, s1) = (read(&control), read(&sim));
    for want in
        ["CPUAffinity=0", "LimitRTPRIO=70\n", "R2G_CPU=0 R2G_FIFO_PRIORITY=70", "/gyms/pick_block_plate/scene.toml"]
    {
        assert!(c1.contains(want), "control drop-in lacks {want:?}:\n{c1}");
    }
    assert!(s1.contains("R2G_RENDER_HZ=5\n") && s1.contains("\"R2G_SIM_ARGS=\"\n"), "sim drop-in:\n{s1}");
    // The units run the binaries this install checked: their folder is in every drop-in.
    let bin = integration_tests::bin_dir().canonicalize().expect("bin dir");
    assert!(c1.contains(&format!("\"R2G_BIN_DIR={}\"\n", bin.display())), "control drop-in:\n{c1}");
    assert!(s1.contains(&format!("\"R2G_BIN_DIR={}\"\n", bin.display())), "sim drop-in:\n{s1}");

    let instance_toml = root.0.join(format!("etc/r2g/{name}/instance.toml"));
    let out = install(&root.0, &[GYM, "--instance", &name, "--config", instance_toml.to_str().expect("utf-8")]);
    assert!(out.status.success(), "reinstall failed");
    assert_eq!(read(&control), c1);
    assert_eq!(read(&sim), s1);
}

#[test]
fn a_robot_config_with_its_gym_is_copied_into_the_instance() {
    let inputs = Temp::new("robotcfg");
    let robot = inputs.0.join("franka.json");
    let text = "{\"profile\": \"franka\"}\n";
    std::fs::write(&robot, text).expect("robot config");
    let root = Temp::new("robotroot");
    let name = integration_tests::instance("rc");
    let out = install(&root.0, &[robot.to_str().expect("utf-8"), "--gym", GYM, "--instance", &name]);
    assert!(out.status.success(), "install failed");
    let copied = std::fs::read_to_string(root.0.join(format!("etc/r2g/{name}/robot.json"))).expect("copy");
    assert_eq!(copied, text);
    let drop_in = root.0.join(format!("etc/systemd/system/r2g-control@{name}.service.d/10-r2g.conf"));
    let drop_in = std::fs::read_to_string(drop_in).expect("drop-in");
    assert!(drop_in.contains("/gyms/pick_block_plate/scene.toml"), "{drop_in}");
}

#[test]
fn the_calibration_files_are_copied_beside_the_robot_config() {
    let inputs = Temp::new("calcfg");
    std::fs::create_dir_all(inputs.0.join("cal")).expect("cal dir");
    let tcp = "{\"flange_from_tcp\": [[1,0,0,0],[0,1,0,0],[0,0,1,0.105],[0,0,0,1]]}\n";
    std::fs::write(inputs.0.join("cal/tcp.json"), tcp).expect("tcp file");
    let robot = inputs.0.join("franka.json");
    let text =
        r#"{"profile": "franka", "calibration": {"tcp": "cal/tcp.json", "cameras": {"wrist": "cal/none.json"}}}"#;
    std::fs::write(&robot, text).expect("robot config");
    let root = Temp::new("calroot");
    let name = integration_tests::instance("cal");
    let out = install(&root.0, &[robot.to_str().expect("utf-8"), "--gym", GYM, "--instance", &name]);
    assert!(out.status.success(), "install failed");
    // the missing camera file: a note, and the instance reports it missing
    assert!(String::from_utf8_lossy(&out.stderr).contains("calibration of camera wrist"), "no note");
    let etc = root.0.join(format!("etc/r2g/{name}"));
    assert_eq!(std::fs::read_to_string(etc.join("calibration/tcp.json")).expect("tcp copy"), tcp);
    assert!(!etc.join("calibration/camera-wrist.json").exists());
    // the copied config names the copies, relative to itself
    let copied: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(etc.join("robot.json")).expect("copy")).expect("json");
    assert_eq!(copied["calibration"]["tcp"], "calibration/tcp.json");
    assert_eq!(copied["calibration"]["cameras"]["wrist"], "calibration/camera-wrist.json");
    assert_eq!(copied["profile"], "franka");

    // a TCP file that is not there: refused (r2g-control would not start), nothing written
    std::fs::remove_file(inputs.0.join("cal/tcp.json")).expect("remove");
    let root = Temp::new("calroot2");
    let out = install(&root.0, &[robot.to_str().expect("utf-8"), "--gym", GYM, "--instance", &name]);
    assert!(!out.status.success());
    assert!(String::from_utf8_lossy(&out.stderr).contains("calibration.tcp"), "no reason");
    assert!(entries(&root.0).is_empty(), "{:?}", entries(&root.0));
}

/// Every file and folder under `dir`.
fn entries(dir: &Path) -> Vec<PathBuf> {
    let mut out = Vec::new();
    for e in std::fs::read_dir(dir).expect("read dir").flatten() {
        out.push(e.path());
        if e.path().is_dir() {
            out.extend(entries(&e.path()));
        }
    }
    out
}

#[test]
fn bad_input_is_refused_with_the_key_and_writes_nothing() {
    let inputs = Temp::new("inputs");
    let file = |n: &str, text: &str| -> String {
        let p = inputs.0.join(n);
        std::fs::write(&p, text).expect("input file");
        p.display().to_string()
    };
    let unknown = file("unknown.toml", "cpu = 0\ncpus = 1\n");
    let far_cpu = file("far.toml", "cpu = 4096\n");
    let prio = file("prio.toml", "fifo_priority = 99\n");
    let kind = file("kind.toml", "render_hz = \"fast\"\n");
    let table = file("table.toml", "[control]\ncpu = 0\n");
    let robot = file("robot.json", "{\"profile\": \"simulation\"}\n");
    let llm = file("llm.toml", "agent_llm = \"/nonexistent/endpoint.toml\"\n");
    let franka = file("franka.json", "{\"profile\": \"franka\"}\n");
    let hand_only = file("hand.toml", "fci_gripper = true\n");
    // A binaries' folder with everything but r2g-fci.
    let no_fci_bin = inputs.0.join("no-fci");
    std::fs::create_dir_all(&no_fci_bin).expect("no-fci dir");
    for b in ["r2g", "r2g-control", "r2g-sim"] {
        std::os::unix::fs::symlink(integration_tests::bin_dir().join(b), no_fci_bin.join(b)).expect("symlink");
    }
    let no_fci_bin = no_fci_bin.display().to_string();
    let empty_bin = inputs.0.join("bin");
    std::fs::create_dir_all(&empty_bin).expect("bin dir");
    let empty_bin = empty_bin.display().to_string();
    let long = "x".repeat(33);
    let cases: Vec<(Vec<&str>, Vec<&str>)> = vec![
        (vec![GYM, "--instance", "ok1", "--config", &unknown], vec!["unknown key \"cpus\"", "accepted keys: cpu,"]),
        (vec![GYM, "--instance", "ok1", "--cpu", "4096"], vec!["--cpu 4096 is out of range", "online CPUs are"]),
        (
            vec![GYM, "--instance", "ok1", "--config", &far_cpu],
            vec!["cpu (in", "= 4096 is out of range", "online CPUs"],
        ),
        (vec![GYM, "--instance", "ok1", "--config", &prio], vec!["fifo_priority", "= 99 is out of range", "1..=98"]),
        (vec![GYM, "--instance", "ok1", "--config", &kind], vec!["render_hz", "is a string", "0..=60"]),
        (vec![GYM, "--instance", "ok1", "--config", &table], vec!["unknown key \"control\"", "accepted keys"]),
        (vec!["no_such_gym", "--instance", "ok1"], vec!["no gym 'no_such_gym'", "pick_block_plate"]),
        (vec![&robot, "--instance", "ok1"], vec!["is a robot config", "--gym"]),
        (vec![GYM, "--instance", "ok1", "--config", &llm], vec!["agent_llm", "endpoint TOML file"]),
        (vec![GYM, "--instance", "bad name"], vec!["--instance \"bad name\"", "A-Z a-z 0-9 _ -"]),
        (vec![GYM, "--instance", &long], vec!["--instance", "1-32 characters"]),
        (vec![GYM, "--instance", "ok1", "--bin-dir", &empty_bin], vec!["has no executable r2g", "--bin-dir"]),
        // A real arm: what `r2g up --fci` refuses (the simulation profile), an address the unit's
        // firewall cannot take, a hand without an arm, and a build without r2g-fci.
        (
            vec![GYM, "--instance", "ok1", "--fci", "172.16.0.2"],
            vec!["r2g-fci for the arm at 172.16.0.2", "wall mode with the franka profile", "--gym"],
        ),
        (
            vec![&franka, "--gym", GYM, "--instance", "ok1", "--fci", "panda.lab"],
            vec!["--fci \"panda.lab\"", "IPv4 address", "not a host name"],
        ),
        (vec![GYM, "--instance", "ok1", "--config", &hand_only], vec!["fci_gripper (in", "needs fci"]),
        (
            vec![&franka, "--gym", GYM, "--instance", "ok1", "--fci", "172.16.0.2", "--bin-dir", &no_fci_bin],
            vec!["has no executable r2g-fci"],
        ),
    ];
    for (args, wanted) in cases {
        let root = Temp::new("bad");
        let out = install(&root.0, &args);
        let stderr = String::from_utf8_lossy(&out.stderr);
        assert_eq!(out.status.code(), Some(1), "{args:?} must be refused: {stderr}");
        for w in wanted {
            assert!(stderr.contains(w), "{args:?}: the message lacks {w:?}:\n{stderr}");
        }
        let left = entries(&root.0);
        assert!(left.is_empty(), "{args:?} wrote {left:?}");
    }
    // As for `r2g up`, the hand needs the arm: refused by the argument parser (exit status 2).
    let root = Temp::new("bad");
    let out = install(&root.0, &[GYM, "--instance", "ok1", "--fci-gripper"]);
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert_eq!(out.status.code(), Some(2), "--fci-gripper without --fci must be refused: {stderr}");
    assert!(stderr.contains("--fci <FCI>"), "{stderr}");
    assert!(entries(&root.0).is_empty(), "--fci-gripper without --fci wrote something");
}

/// A robot config naming a Robotiq 2F-85 and two cameras (a RealSense and a UVC camera) installs
/// a gripper unit and one camera unit per camera, each verifying without a word and each allowed
/// exactly its own device and the groups that own such devices.
#[test]
fn devices_get_units_that_open_only_their_own_devices() {
    let root = Temp::new("devices");
    let name = integration_tests::instance("devices");
    let cfg = root.0.join("cfg");
    std::fs::create_dir_all(&cfg).expect("cfg dir");
    let cam = r#"{"base_from_camera": [[1, 0, 0, 0.5], [0, 1, 0, 0], [0, 0, 1, 1.2], [0, 0, 0, 1]]}"#;
    std::fs::write(cfg.join("front.json"), cam).expect("write");
    std::fs::write(cfg.join("side.json"), cam).expect("write");
    std::fs::write(
        cfg.join("robot.json"),
        r#"{"profile": "franka",
            "gripper": {"driver": "robotiq_2f85", "port": "/dev/ttyUSB0"},
            "calibration": {"cameras": {"front": "front.json", "side": "side.json"}},
            "cameras": {"front": {"driver": "realsense", "serial": "123456789012"},
                        "side": {"driver": "uvc", "device": "/dev/video2"}}}"#,
    )
    .expect("write");
    let robot_json = cfg.join("robot.json").display().to_string();
    let out = install(&root.0.join("root"), &[&robot_json, "--gym", GYM, "--instance", &name]);
    assert!(out.status.success(), "install failed: {}", String::from_utf8_lossy(&out.stderr));
    let dir = root.0.join("root/etc/systemd/system");
    let gripper = format!("r2g-robotiq@{name}.service");
    let front = format!("r2g-camera@{name}.front.service");
    let side = format!("r2g-camera@{name}.side.service");
    for unit in [&gripper, &front, &side, &format!("r2g@{name}.target")] {
        let out = run(Command::new(tool("systemd-analyze")).arg("verify").arg(dir.join(unit)));
        let stderr = String::from_utf8_lossy(&out.stderr);
        assert!(out.status.success() && stderr.trim().is_empty(), "systemd-analyze verify {unit}:\n{stderr}");
    }
    let target = directives(&dir, "r2g@.target", &name);
    let wants = values(&target, "Wants");
    for unit in [&gripper, &front, &side] {
        assert!(wants.contains(&unit.as_str()), "the target does not want {unit}: {wants:?}");
    }

    let g = directives(&dir, "r2g-robotiq@.service", &name);
    assert_eq!(values(&g, "DevicePolicy"), ["closed"]);
    // The USB serial driver's class: a path would be fixed to the device number it has at start.
    assert_eq!(values(&g, "DeviceAllow"), ["char-ttyUSB", "rw"]);
    assert_eq!(values(&g, "SupplementaryGroups"), ["dialout"]);
    assert_eq!(values(&g, "PrivateNetwork"), ["yes"]);
    assert_eq!(values(&g, "BindPaths"), [format!("/run/r2g/{name}/shm:/dev/shm")]);
    let f = directives(&dir, "r2g-camera@.service", &format!("{name}.front"));
    assert_eq!(values(&f, "DeviceAllow"), ["char-usb_device", "rw"]);
    assert_eq!(values(&f, "SupplementaryGroups"), ["video"]);
    assert_eq!(values(&f, "BindPaths"), [format!("/run/r2g/{name}/shm:/dev/shm")]);
    let env = values(&f, "Environment");
    for want in [format!("R2G_INSTANCE={name}"), "R2G_CAMERA_ARGS=--camera".to_string(), "123456789012".into()] {
        assert!(env.contains(&want.as_str()), "the front camera unit lacks {want}: {env:?}");
    }
    let s = directives(&dir, "r2g-camera@.service", &format!("{name}.side"));
    assert_eq!(values(&s, "DeviceAllow"), ["/dev/video2", "rw"]);
    // r2g-sim lists both cameras for agents and renders neither (as `r2g up` tells it).
    let sim = directives(&dir, "r2g-sim@.service", &name);
    let env = values(&sim, "Environment");
    for cam in ["front", "side"] {
        assert!(env.windows(2).any(|w| w == ["--camera-host", cam]), "r2g-sim is not told of camera {cam}: {env:?}");
    }
    for unit in [&gripper, &front] {
        let score = security(&dir, unit);
        assert!(score <= 3.0, "{unit} exposure {score} > 3.0");
    }
}
