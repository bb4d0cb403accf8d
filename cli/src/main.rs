//! r2g: the one command a person types.

use std::io::Write;
use std::time::Duration;

use agent_host::session;
use clap::{Parser, Subcommand, ValueEnum};
use ipc_schema::process;
use ipc_schema::Mode;
use runtime::launch::{self, Instance, UpOptions};

mod blender_cmd;
mod compare_cmd;
mod judge_cmd;
mod kin;
mod reconstruct_cmd;
mod render_cmd;
mod service;
mod skills_cmd;

/// Counts allocations inside ticks, so `bench tick-compute` can report them.
#[global_allocator]
static ALLOC: runtime::alloc_count::CountingAlloc = runtime::alloc_count::CountingAlloc;

#[derive(Clone, Copy, Debug, ValueEnum)]
enum ModeArg {
    /// Real time: the runtime ticks at 1 kHz on the wall clock.
    Wall,
    /// Simulated time: runtime and simulator advance together, only while a command executes.
    Lockstep,
}

/// Real2Gym runtime: run gyms, drive them from Python through `robo`, measure latency.
#[derive(Parser, Debug)]
#[command(version, about, long_about = None)]
struct Cli {
    #[command(subcommand)]
    command: Cmd,
}

#[derive(Subcommand, Debug)]
enum Cmd {
    /// Start a gym: sim-host + 1 kHz runtime. Prints `READY <instance>` when `robo` can connect
    /// (set R2G_INSTANCE to the same name), runs until Ctrl-C/SIGTERM, then stops both and
    /// removes their shared memory. The developer's supervisor: when either child dies it stops
    /// the whole instance. Installed as services (deploy/, `r2g service install`), the control
    /// process instead outlives its robot side: it holds the arm, refuses chunks with the
    /// reason, and resumes from fresh state when the robot side is back.
    Up {
        /// Gym name (see `r2g gyms`), gym folder, or scene file.
        gym: String,
        #[arg(long, value_enum, default_value_t = ModeArg::Wall)]
        mode: ModeArg,
        /// Instance name; lets several gyms run side by side.
        #[arg(long, default_value = "default")]
        instance: String,
        /// Camera frames per second (0: no rendering).
        #[arg(long, default_value_t = 10.0)]
        render_hz: f64,
        /// Record the native trace and judge every episode (ended by a reset or by stopping)
        /// into this folder: episode-N.trace.json and episode-N.eval.json.
        #[arg(long)]
        trace_dir: Option<std::path::PathBuf>,
        /// Profile and limits (default: robot-skill/config/robot.json of this checkout).
        #[arg(long)]
        robot_config: Option<std::path::PathBuf>,
        /// Members of this group may clear faults (`r2g clear`), besides root and the user
        /// running the instance.
        #[arg(long)]
        operator_group: Option<String>,
        /// Drive a real Franka arm at this FCI address (host or host:port) instead of the
        /// simulator: r2g-fci becomes the robot side (wall mode, franka profile; no cameras).
        #[arg(long)]
        fci: Option<String>,
        /// Also drive the Franka Hand of that arm (with --fci).
        #[arg(long, requires = "fci")]
        fci_gripper: bool,
        #[command(flatten)]
        placement: PlacementArgs,
        /// Serve gymnasium environments (the `r2g_gym` package's live mode): the evaluator's
        /// verdict and the episode seed on the instance's `env/` services, which `robo` never opens.
        #[arg(long, conflicts_with = "fci")]
        env: bool,
    },
    /// Run one program in the sandbox against a live gym (`r2g up ... --instance NAME`) and
    /// print a JSON result: stdout, stderr, exit, violation, control steps, what was enforced.
    Exec {
        file: std::path::PathBuf,
        #[arg(long, default_value = "default")]
        instance: String,
        /// Waypoints the program may post.
        #[arg(long, default_value_t = 600)]
        budget: u64,
        /// Wall-clock limit, s.
        #[arg(long, default_value_t = 120.0)]
        wall_s: f64,
        /// CPU limit, s.
        #[arg(long, default_value_t = 120)]
        cpu_s: u64,
        /// Refuse reset and post_actions (an observation-only turn).
        #[arg(long)]
        observe_only: bool,
        /// Scratch folder (default: a new one under runs/exec/). Reuse one across the stage
        /// programs of an episode to keep its files and robo_perception's object identities.
        #[arg(long)]
        scratch: Option<std::path::PathBuf>,
        /// Memory folder (e.g. robot-skill/memory): its records are copied into the scratch
        /// folder's memory/ first, and the program's new records appended to it afterwards.
        /// Without it the program gets no memory/.
        #[arg(long)]
        memory: Option<std::path::PathBuf>,
        /// The robot configuration the instance runs with (as given to `r2g up --robot-config`),
        /// shown to the program as robot-skill/config/robot.json; default: the shipped one. The
        /// result warns when it is not the one the instance reports.
        #[arg(long)]
        robot_config: Option<std::path::PathBuf>,
    },
    /// One episode of the stage-code agent loop on a gym this command starts; ends with one JSON
    /// line (success, responses, tokens, wall time split, run_dir).
    Episode {
        #[command(flatten)]
        opts: EpisodeArgs,
        /// After the episode, extract skills from it into the library (as `r2g skills extract`;
        /// the same as `--skills learn`).
        #[arg(long)]
        learn: bool,
        /// Endpoint for the extraction (default: the episode's own; a scripted episode's
        /// extraction replays the gym's recorded extraction answers).
        #[arg(long)]
        learn_llm: Option<String>,
        #[command(flatten)]
        admit: skills_cmd::AdmitArgs,
    },
    /// Several episodes and their metrics (success rate, responses, tokens, time split). Exits 1
    /// when no episode could run at all (every one ended in an error, e.g. an unreachable
    /// endpoint), 0 otherwise, however many tasks failed.
    Batch {
        #[arg(long, default_value_t = 3)]
        episodes: u32,
        #[command(flatten)]
        opts: EpisodeArgs,
        /// Endpoint for the extractions of `--skills learn` (default: the episodes' own; scripted
        /// episodes' extractions replay the gym's recorded extraction answers).
        #[arg(long)]
        learn_llm: Option<String>,
        #[command(flatten)]
        admit: skills_cmd::AdmitArgs,
        #[command(flatten)]
        fleet: FleetArgs,
    },
    /// The skill library (runs/skill-library by default): list, show, extract from a run,
    /// admit, run without a model, select.
    Skills {
        #[command(subcommand)]
        which: skills_cmd::SkillsCmd,
    },
    /// Write (or rewrite) the static HTML viewer of a run folder.
    View { run_dir: std::path::PathBuf },
    /// Operator only: clear an `operator_required` fault of a running instance (Franka profile),
    /// after checking the arm and its surroundings. Sent over the instance's operator socket;
    /// taken from root, the runtime's user or its `--operator-group`. Exits 0 when the runtime
    /// took the request (it prints whether there was a fault), 1 when refused or unreachable.
    Clear {
        #[arg(long, default_value = "default")]
        instance: String,
    },
    /// Stop an instance that `r2g up` runs (SIGTERM to that `r2g up`, by the pid it wrote to
    /// <run folder>/up.pid: $R2G_RUN_DIR/NAME, else /run/r2g/NAME when it exists, else
    /// $XDG_RUNTIME_DIR/r2g/NAME, else /tmp/r2g-<uid>/NAME) and return once it has exited: its processes are stopped and the last
    /// episode's verdict is written (with --trace-dir). Exits 0 when it stopped, 1 when no such
    /// instance runs here or it did not stop in time (nothing else is signalled).
    Down {
        #[arg(long, default_value = "default")]
        instance: String,
        /// How long to wait for it to exit, s.
        #[arg(long, default_value_t = 60.0)]
        timeout_s: f64,
    },
    /// List the gyms of the pack, one name per line.
    Gyms,
    /// Replay a gym's demonstration in lockstep (controller at 1 kHz, one physics step per
    /// tick), then judge the native trace. Ends with the evaluator's JSON line; exit status 0
    /// on success, 1 when the task failed.
    Replay {
        /// Gym name, gym folder, or scene file; with --seeds, --workers or --ray several, or
        /// `all` for the whole pack.
        #[arg(required = true)]
        gyms: Vec<String>,
        #[command(flatten)]
        placement: PlacementArgs,
        /// Replay each gym with seeds 0..N, as one job per replay (a summary JSON at the end).
        #[arg(long)]
        seeds: Option<u64>,
        #[command(flatten)]
        fleet: FleetArgs,
        /// Post no actions at all: the evaluator must then report failure.
        #[arg(long)]
        do_nothing: bool,
        /// Folder for the trace and the evaluation (default: runs/replay).
        #[arg(long, default_value = "runs/replay")]
        out: std::path::PathBuf,
    },
    /// Write a gym's demonstration (demo.csv) from its TCP keyframes (keyframes.toml) with IK.
    AuthorDemo { gym: String },
    /// Import a recorded demonstration into a new gym folder (scene, demo.csv, record.json,
    /// events.json, import.json): `droid <episode folder>` (trajectory.h5 + metadata_*.json) or
    /// `egodex <file.hdf5>` (a hand retargeted to the gripper). The scene is given; the folder
    /// appears whole or not at all. Ends with one JSON line.
    Import {
        #[command(subcommand)]
        which: ImportCmd,
    },
    /// Expand a gym into a pool of variants (object size and pose, support height, friction and
    /// mass, distractors, lighting and colours), each factor swept alone for its feasible range
    /// first, then N candidates combining one to three factors; the demonstration is adapted to
    /// the moved objects and re-solved with IK; failures are shrunk toward the parent; only
    /// variants that pass `r2g validate` are kept, near-duplicates removed. Each variant is a
    /// gym folder (usable by up, replay, episode, batch). Writes report.json and
    /// contact_sheet.png into the pool; ends with one JSON line.
    Augment {
        /// Gym name, gym folder, or scene file.
        gym: String,
        #[arg(long, default_value_t = 50)]
        candidates: usize,
        #[arg(long, default_value_t = 1)]
        seed: u64,
        /// The pool folder (must not exist, or be empty).
        #[arg(long)]
        out: std::path::PathBuf,
        /// Candidates validated at once (threads; each a self-contained unit of work).
        #[arg(long, default_value_t = 1)]
        jobs: usize,
        /// Times a failed candidate is shrunk toward its parent before it is dropped.
        #[arg(long, default_value_t = 2)]
        shrink_tries: usize,
        /// Skip the contact sheet (no rendering at all).
        #[arg(long)]
        no_sheet: bool,
        /// Only these factors (comma-separated): object_size, object_pose, support_height,
        /// friction_mass, distractors, visual.
        #[arg(long, value_delimiter = ',')]
        factors: Vec<String>,
        /// At most this many sweep levels per parameter and side (nearest the parent first).
        #[arg(long)]
        levels: Option<usize>,
        /// Validate candidates as fleet jobs (`r2g validate <variant>` each): --workers N on this
        /// machine, or --ray auto|ADDRESS one Ray task per candidate (the pool folder must be
        /// on storage every node sees).
        #[command(flatten)]
        fleet: FleetArgs,
    },
    /// Run the validation gate: the gym executed natively from its inputs (lockstep, in
    /// process), every input hashed into evidence.json; checks: no initial penetration and at
    /// rest, every waypoint reachable, event timing against the source, task success, worst
    /// penetration, final stability. Ends with one JSON line; exit status 1 when a check fails.
    Validate {
        /// Gym name, gym folder, or scene file.
        gym: String,
        #[arg(long, default_value_t = 0)]
        seed: u64,
        /// Folder for evidence.json (default: runs/validate/<gym folder>).
        #[arg(long)]
        out: Option<std::path::PathBuf>,
        /// Also write the native trace (trace.json).
        #[arg(long)]
        keep_trace: bool,
    },
    /// A gym's compiled scene in Blender (.blend): every drawn geom, the cameras and lights, and
    /// every body's pose keyframed from a native trace (default: the demonstration replayed in
    /// lockstep); with --render, Cycles (CPU) images of chosen instants and cameras.
    Blender(blender_cmd::BlenderArgs),
    /// A gym rendered by MuJoCo into a BOP scene folder (scene_camera.json, rgb/, depth/,
    /// mask_visib/, scene_gt.json, joints.json): the scene at rest, or a native trace's states
    /// at given times, from the scene's cameras or those of a BOP scene_camera.json.
    Render(render_cmd::RenderArgs),
    /// A gym folder from RGB-D frames in the BOP scene layout: the robot's pixels removed by
    /// forward kinematics, the table and objects fitted (primitives, compounds, convex hulls),
    /// settled by physics, and checked by rendering it from every source camera (figures in
    /// <out>/reconstruction.json). Written whole or not at all; ends with one JSON line.
    Reconstruct(reconstruct_cmd::ReconstructArgs),
    /// The same instants drawn by MuJoCo (`r2g render`) and Blender (Cycles), and the source
    /// frames when given, side by side in one PNG sheet, with per-object silhouette IoU
    /// (`<sheet>.json` beside it, both renders in `<sheet>.renders/`).
    Compare(compare_cmd::CompareArgs),
    /// Grade a gym with a model and our rubric (after the paper's appendix): source frames,
    /// MuJoCo and Blender images of the same instants, the demonstration and the native verdict
    /// go to the endpoint; scores, justifications, model and tokens go to <out>/judge.json.
    /// Ends with one JSON line. Scores from `--llm scripted` test the mechanics only.
    Judge(judge_cmd::JudgeArgs),
    /// Kinematics over JSON lines: reads one request per stdin line, answers one line each.
    Kin {
        #[command(subcommand)]
        which: KinCmd,
    },
    /// systemd services of one instance on a robot PC: `install` writes the units and the
    /// configuration, `status` shows tick health (deploy/README.md).
    Service {
        #[command(subcommand)]
        which: service::ServiceCmd,
    },
    /// Run a benchmark; prints a table and, as the last line, one JSON object.
    Bench {
        #[command(subcommand)]
        which: BenchCmd,
    },
}

#[derive(Subcommand, Debug)]
enum ImportCmd {
    /// A DROID raw episode: a folder with trajectory.h5 and metadata_*.json. Joints are gated on
    /// our FK against the recorded flange pose (panda_link8 in panda_link0).
    Droid {
        episode: std::path::PathBuf,
        /// The scene the demonstration happened in (its robot, objects, task).
        #[arg(long)]
        scene: String,
        /// The new gym folder (must not exist, or be empty).
        #[arg(long)]
        out: std::path::PathBuf,
        /// Largest accepted FK position error, m.
        #[arg(long, default_value_t = 0.01)]
        fk_gate_m: f64,
        /// Largest accepted FK rotation error, rad.
        #[arg(long, default_value_t = 0.05)]
        fk_gate_rad: f64,
    },
    /// An EgoDex episode (.hdf5): the hand's pinch retargeted to the parallel gripper.
    Egodex {
        episode: std::path::PathBuf,
        #[arg(long)]
        scene: String,
        #[arg(long)]
        out: std::path::PathBuf,
        /// left, right, or auto (the hand seen most that opens and closes).
        #[arg(long, default_value = "auto")]
        hand: String,
        /// JSON {"base_from_world": 4x4 row-major}: ARKit world to robot base. Without it the
        /// registration is estimated from the task's object and target in the scene.
        #[arg(long)]
        registration: Option<std::path::PathBuf>,
        /// Frames whose pinch points are less confident than this are dropped.
        #[arg(long, default_value_t = 0.5)]
        min_confidence: f64,
    },
}

/// Where the objects start: `--seed` and `--perturb` (sim_host::placement).
#[derive(clap::Args, Debug, Clone, Default)]
struct PlacementArgs {
    /// Augmentation seed (0: the scene as written; otherwise each object moves by its own
    /// jitter, and the objects --perturb names by its ranges). `r2g batch` gives episode i the
    /// seed SEED + i.
    #[arg(long, default_value_t = 0)]
    seed: u64,
    /// Move free objects further, drawn from the seed and clear of everything else:
    /// `xy=0.05,yaw=30[,objects=block+plate]` (up to ±5 cm in x and y, ±30 degrees of yaw).
    #[arg(long, value_name = "SPEC")]
    perturb: Option<sim_host::placement::Perturbation>,
}

impl PlacementArgs {
    fn check(&self) -> anyhow::Result<()> {
        if self.perturb.is_some() && self.seed == 0 {
            anyhow::bail!(
                "--perturb draws the placement from the seed: give --seed N (N > 0); seed 0 is the scene as written"
            );
        }
        Ok(())
    }

    /// The arguments r2g-sim takes for this placement.
    fn sim_args(&self) -> Vec<String> {
        let mut v = vec!["--seed".to_string(), self.seed.to_string()];
        if let Some(p) = &self.perturb {
            v.extend(["--perturb".to_string(), p.to_string()]);
        }
        v
    }
}

/// Options of `r2g episode` and `r2g batch`.
#[derive(clap::Args, Debug, Clone)]
struct EpisodeArgs {
    /// Gym name (see `r2g gyms`), gym folder, or scene file.
    gym: String,
    /// An endpoint TOML file (provider, base_url, model, api_key_env, ...), "scripted" (the
    /// gym's recorded conversation), "scripted:<conversation.json | cassette.jsonl>" (answers by
    /// turn), "record:<endpoint.toml>" (the endpoint, each answer kept in <run>/cassette.jsonl)
    /// or "replay:<cassette.jsonl>" (the recorded answers, no network; a request not recorded
    /// is an error).
    #[arg(long, default_value = "scripted")]
    llm: String,
    /// Wire format for `--llm scripted`: openai or anthropic.
    #[arg(long, default_value = "openai")]
    provider: String,
    #[arg(long, default_value_t = 50)]
    max_decisions: u32,
    /// Waypoints one program may post.
    #[arg(long, default_value_t = 600)]
    control_steps: u64,
    /// Run the gym in wall-clock time instead of lockstep.
    #[arg(long)]
    wall: bool,
    /// Run folder (default: runs/episodes/<gym>-<stamp>; for a batch, its folder).
    #[arg(long)]
    out: Option<std::path::PathBuf>,
    #[arg(long)]
    robot_config: Option<std::path::PathBuf>,
    /// Wall-clock limit per program, s.
    #[arg(long, default_value_t = 120.0)]
    wall_s: f64,
    /// Folder of append-only memory records (default: robot-skill/memory).
    #[arg(long)]
    memory: Option<std::path::PathBuf>,
    #[command(flatten)]
    placement: PlacementArgs,
    /// `use`: give the episode skills selected from the library (see --library); `learn`: for
    /// `r2g episode`, extract skills from it afterwards; for `r2g batch`, the paper's protocol —
    /// per seed an episode without skills, extraction from it, then an episode on the same seed
    /// with the selected skills, figures per arm; `off`: none.
    #[arg(long, default_value = "off", value_parser = ["off", "use", "learn"])]
    skills: String,
    /// The skill library (default: runs/skill-library).
    #[arg(long)]
    library: Option<std::path::PathBuf>,
}

impl EpisodeArgs {
    fn library(&self) -> std::path::PathBuf {
        self.library.clone().unwrap_or_else(skills::learn::default_library)
    }

    /// The episode options, with the library's skills when `--skills use`.
    fn episode_opts(self) -> anyhow::Result<session::EpisodeOpts> {
        let lib = self.library();
        let use_skills = self.skills == "use";
        let o: session::EpisodeOpts = self.try_into()?;
        if use_skills {
            skills::learn::with_skills(&o, &lib)
        } else {
            Ok(o)
        }
    }
}

impl TryFrom<EpisodeArgs> for session::EpisodeOpts {
    type Error = anyhow::Error;

    fn try_from(a: EpisodeArgs) -> anyhow::Result<Self> {
        a.placement.check()?;
        Ok(Self {
            gym: a.gym,
            llm: a.llm,
            provider: a.provider,
            max_decisions: a.max_decisions,
            control_steps: a.control_steps,
            wall: a.wall,
            out: a.out,
            robot_config: a.robot_config,
            wall_s: a.wall_s,
            memory: a.memory,
            seed: a.placement.seed,
            perturb: a.placement.perturb.map(|p| p.to_string()),
            skills: None,
            library: None,
        })
    }
}

/// Where the episodes of a batch run (default: one after the other in this process).
#[derive(clap::Args, Debug, Clone)]
struct FleetArgs {
    /// Run the episodes as Ray tasks: `auto` (the running cluster, else a local one for this
    /// batch) or a cluster's address (fleet/MULTINODE.md). Needs `ray` (requirements-ray.txt).
    #[arg(long, value_name = "auto|ADDRESS")]
    ray: Option<String>,
    /// Run this many episodes at once on this machine, each in its own process group and
    /// shared-memory prefix (no Ray); with --ray, at most this many at once on the cluster.
    #[arg(long)]
    workers: Option<usize>,
}

/// Options shared by `r2g kin fk` and `r2g kin ik`.
#[derive(clap::Args, Debug)]
struct KinArgs {
    /// `panda`, `fr3` (the shipped description with that robot's limits) or a URDF file
    /// (read with the Panda acceleration and jerk limits).
    #[arg(long, default_value = "panda")]
    robot: String,
    /// Frame to compute or place (a link name, `tcp` or `flange`); default: the TCP.
    #[arg(long)]
    frame: Option<String>,
    /// The URDF link that is the TCP.
    #[arg(long, default_value = "hand_tcp")]
    tcp: String,
}

#[derive(Subcommand, Debug)]
enum KinCmd {
    /// `{"q":[7 numbers]}` → `{"position":[x,y,z],"quaternion":[x,y,z,w]}` (base frame).
    Fk {
        #[command(flatten)]
        args: KinArgs,
    },
    /// `{"position":[3],"quaternion":[x,y,z,w],"seed":[7]}` →
    /// `{"ok":bool,"q":[7],"position_error":m,"rotation_error":rad,...}`; tolerances 1e-5 m and
    /// 1e-5 rad, joint limits kept. Without "seed" the middle of the joint ranges is the seed.
    Ik {
        #[command(flatten)]
        args: KinArgs,
    },
}

#[derive(Subcommand, Debug)]
enum BenchCmd {
    /// The real 1 kHz tick loop (with sim-host stepping and rendering) beside a bare
    /// clock_nanosleep loop, measured the same way in the same run.
    Tick {
        /// Seconds each loop runs.
        #[arg(long, default_value_t = 10.0)]
        seconds: f64,
        #[arg(long, default_value = "pick_block_plate")]
        gym: String,
    },
    /// Python round trips through `robo` (state only, two PNGs, raw arrays + depth) and
    /// post_actions submission-to-first-motion latency, beside a Unix-socket baseline.
    Robo {
        /// Round trips per figure (state only; fewer for images).
        #[arg(long, default_value_t = 2000)]
        samples: usize,
        #[arg(long, default_value = "pick_block_plate")]
        gym: String,
    },
    /// Host overhead per decision of the agent loop (scripted endpoint), beside the same stage
    /// programs run bare.
    Agent {
        #[arg(long, default_value_t = 3)]
        episodes: u32,
    },
    /// Local perception over the pack's graspable objects at 640x480: segmentation IoU against
    /// MuJoCo's own segmentation, lift rate of the example pick program (judged from the native
    /// trace), segmentation and grasp times beside a back-projection baseline.
    Perception {
        /// Only these gyms (comma-separated); default every gym (IoU and lifts for those with graspable objects).
        #[arg(long, value_delimiter = ',')]
        gyms: Vec<String>,
        /// Segmentation and grasp proposals only, no pick attempts.
        #[arg(long)]
        no_lift: bool,
    },
    /// The same as `tick` under an agent's load: a Python program polls get_state (with both
    /// PNG images) and posts joint chunks through `robo` the whole time.
    Jitter {
        #[arg(long, default_value_t = 60.0)]
        seconds: f64,
        #[arg(long, default_value = "pick_block_plate")]
        gym: String,
    },
    /// Every benchmark in turn (ipc, robo, agent, perception, jitter, tick, tick-compute, ik,
    /// limiter-fuzz, sim), with a progress bar; writes bench-report/ (summary.md, one JSON per benchmark, PNG plots).
    All {
        /// Seconds of the jitter run.
        #[arg(long, default_value_t = 60.0)]
        jitter_seconds: f64,
        #[arg(long, default_value = "bench-report")]
        out: std::path::PathBuf,
        /// Small runs of everything (for checking the pipeline, not for figures).
        #[arg(long)]
        quick: bool,
    },
    /// Publish→receive latency between two processes for a robot state, a joint command, a
    /// 640×480 RGB frame and an RGB-D frame, through iceoryx2 (zero-copy), a Unix domain socket,
    /// TCP loopback and ZeroMQ.
    Ipc {
        /// Only the pairs whose "transport:payload" contains this (e.g. "uds", ":frame").
        #[arg(long)]
        only: Option<String>,
    },
    /// Tick-to-command latency of the real loop while a client posts the heaviest accepted and
    /// rejected ee_pose chunks back to back, beside the bare loop in the same run; with chunk
    /// checks on the planner thread, then on the tick thread (the old way).
    Accept {
        /// Seconds of chunks per run.
        #[arg(long, default_value_t = 20.0)]
        seconds: f64,
        /// Only one run: `planner` or `tick`.
        #[arg(long)]
        only: Option<String>,
    },
    /// A 5 s joint move through `robo` on sim-host and on r2g-fci against franka-sim (the
    /// Franka network protocol on 127.0.0.1), in one run: final error, the runtime's wake and
    /// tick-to-command latency, and the FCI cycle (packets lost, reply latency vs the budget).
    Fci {
        /// Run franka-sim without its motion-limit check (on by default, as on a real arm).
        #[arg(long)]
        lenient_peer: bool,
    },
    /// Cost of one controller tick (interpolation, limiter, checks) following valid chunks,
    /// with allocations inside ticks counted, beside FK + Jacobian alone.
    TickCompute {
        #[arg(long, default_value_t = 200_000)]
        ticks: u64,
    },
    /// Adversarial chunks (NaN, infinities, huge jumps, wrong lengths, absurd rates, resets,
    /// chunks mid-motion) through the controller; every command judged by a limit monitor.
    LimiterFuzz {
        #[arg(long, default_value_t = 1_000_000)]
        chunks: u64,
        #[arg(long, default_value_t = 1)]
        seed: u64,
    },
    /// Full-pose IK on random reachable Panda TCP poses: success rate and solve times, beside
    /// plain FK, a naive undamped pseudo-inverse solver and (when importable) Pinocchio.
    Ik {
        /// Targets as `r2g kin ik` input lines instead of random ones.
        #[arg(long)]
        targets: Option<std::path::PathBuf>,
        /// Number of random targets (ignored with --targets).
        #[arg(long, default_value_t = 10_000)]
        count: usize,
    },
    /// Skill transfer: per gym, a skill extracted from one scripted episode, run without a model on
    /// N seeds with the objects moved (default ±5 cm, ±30°), against the same procedure replaying
    /// the episode's absolute targets, natively judged (gyms with recorded conversations).
    Skills {
        #[arg(long, value_delimiter = ',', default_value = "pick_block_plate")]
        gyms: Vec<String>,
        #[arg(long, default_value_t = 50)]
        seeds: u64,
        #[arg(long, default_value_t = 5001)]
        first_seed: u64,
        #[arg(long, default_value = "xy=0.05,yaw=30")]
        perturb: sim_host::placement::Perturbation,
        /// Runs at a time (more than the cores is oversubscription).
        #[arg(long, default_value_t = 2)]
        jobs: usize,
        #[arg(long, default_value = "bench-report/skills")]
        out: std::path::PathBuf,
    },
    /// Physics in lockstep with the 1 kHz controller: real-time factor per gym while replaying
    /// its demonstration, beside MuJoCo stepping alone; and render time per 640×480 frame,
    /// RGB and RGB-D.
    Sim {
        /// Only these gyms (default: all).
        gyms: Vec<String>,
        /// Frames rendered per camera and mode.
        #[arg(long, default_value_t = 30)]
        frames: usize,
    },
    /// Wall mode with cameras and a Python agent posting joint chunks for N minutes: missed
    /// ticks and wake p99.9 beside a bare loop, RSS growth of every process, shared-memory files
    /// before and after, and the ticks missed while the agent is stopped (SIGSTOP) mid-run.
    Soak {
        #[arg(long, default_value_t = 30.0)]
        minutes: f64,
        #[arg(long, default_value = "pick_block_plate")]
        gym: String,
        /// Seconds the agent is stopped in the middle of the run.
        #[arg(long, default_value_t = 30.0)]
        stall_s: f64,
        /// Seconds between samples of RSS and tick health.
        #[arg(long, default_value_t = 5.0)]
        sample_s: f64,
    },
    /// Episodes per minute of lockstep demonstration replays and scripted agent episodes at 1, 2
    /// and N workers, on local workers and as tasks of a local Ray cluster it starts and stops;
    /// Ray's overhead per task and the parallel efficiency; as root, Ray's overhead per task
    /// across three nodes made of namespaces on this machine (overhead, not speed-up).
    Batch {
        /// The largest worker count (above the cores: oversubscription, labelled so).
        #[arg(long, default_value_t = 4)]
        workers: usize,
        /// Replays per configuration.
        #[arg(long, default_value_t = 8)]
        replays: usize,
        /// Scripted agent episodes per configuration.
        #[arg(long, default_value_t = 4)]
        agents: usize,
    },
    /// The receiving process of `r2g bench ipc` (started by it).
    #[command(hide = true)]
    IpcPeer {
        #[arg(long)]
        transport: String,
        #[arg(long)]
        payload: String,
        #[arg(long)]
        addr: String,
        #[arg(long, default_value_t = 1)]
        cpu: usize,
    },
}

fn main() {
    let cli = Cli::parse();
    let r = match cli.command {
        Cmd::Up {
            gym,
            mode,
            instance,
            render_hz,
            trace_dir,
            robot_config,
            operator_group,
            fci,
            fci_gripper,
            placement,
            env,
        } => {
            // Only `up` waits for the stop signals to shut its instance down in order; every other
            // command ends at once on them, and its instances' processes follow (die_with_parent).
            process::install_stop_signals();
            let rc = robot_config.unwrap_or_else(launch::default_robot_config);
            let control_args = operator_group.map(|g| vec!["--operator-group".into(), g]).unwrap_or_default();
            let side = match fci {
                Some(address) => launch::RobotSide::Fci {
                    address,
                    extra: if fci_gripper { vec!["--gripper".into()] } else { vec![] },
                },
                None => launch::RobotSide::Sim,
            };
            let mut sim_args: Vec<String> =
                trace_dir.map(|d| vec!["--trace-dir".into(), d.display().to_string()]).unwrap_or_default();
            if env {
                sim_args.push("--env".into());
            }
            up(&gym, mode, &instance, render_hz, sim_args, rc, control_args, &side, &placement)
        }
        Cmd::Down { instance, timeout_s } => down(&instance, timeout_s),
        Cmd::Clear { instance } => runtime::operator::clear_fault(&instance).map(|(_cleared, reason)| {
            println!("{reason}");
            0
        }),
        Cmd::Episode { opts, learn, learn_llm, admit } => {
            let library = opts.library();
            let learn = learn || opts.skills == "learn";
            let use_skills = opts.skills == "use";
            let learn_llm = learn_llm.unwrap_or_else(|| skills::learn::extraction_llm(&opts.llm));
            opts.episode_opts().and_then(|o| session::episode(&o)).and_then(|r| {
                println!("{}", serde_json::to_string(&r)?);
                if learn {
                    let lo = skills::learn::LearnOpts {
                        admit: admit.opts(),
                        ..skills::learn::LearnOpts::new(library.clone(), &learn_llm)
                    };
                    let l = skills::learn::learn(std::path::Path::new(&r.run_dir), &lo)?;
                    eprintln!(
                        "r2g episode --learn ({} extraction): wrote {:?}, dropped {}, admissions {:?}",
                        l.llm_source,
                        l.merge.written,
                        l.merge.dropped.len(),
                        l.admissions.iter().map(|a| (&a.skill, a.validated)).collect::<Vec<_>>()
                    );
                }
                if use_skills {
                    let lo = skills::learn::LearnOpts::new(library.clone(), "scripted");
                    skills::learn::record_use(&library, std::path::Path::new(&r.run_dir), &lo)?;
                }
                Ok(if r.success { 0 } else { 1 })
            })
        }
        Cmd::Skills { which } => skills_cmd::run(which),
        Cmd::Batch { episodes, opts, learn_llm, admit, fleet } if opts.skills == "learn" => {
            let library = opts.library();
            let learn_llm = learn_llm.unwrap_or_else(|| skills::learn::extraction_llm(&opts.llm));
            let lo =
                skills::learn::LearnOpts { admit: admit.opts(), ..skills::learn::LearnOpts::new(library, &learn_llm) };
            let backend = fleet::Backend::from_args(fleet.ray.as_deref(), fleet.workers);
            opts.try_into().and_then(|o: session::EpisodeOpts| {
                skills::learn::protocol(&o, episodes, &lo, backend.as_ref(), |arm, i, r| match r {
                    Ok(v) => {
                        eprintln!("r2g batch: seed {i} {arm}: success {} in {} responses", v["success"], v["responses"])
                    }
                    Err(e) => eprintln!("r2g batch: seed {i} {arm}: {e:#}"),
                })
                .map(|v| {
                    eprintln!("{}", v["label"].as_str().unwrap_or_default());
                    eprintln!(
                        "{:<16} {:>8} {:>10} {:>11} {:>10} {:>8}",
                        "arm", "success", "responses", "tokens in", "tokens out", "wall s"
                    );
                    for (name, k) in [("without skills", "without_skills"), ("with skills", "with_skills")] {
                        let a = &v[k];
                        let f = |m: &str| a[m].as_f64().unwrap_or(0.0);
                        eprintln!(
                            "{name:<16} {:>8.2} {:>10.1} {:>11.0} {:>10.0} {:>8.1}",
                            f("success_rate"),
                            f("responses_mean"),
                            f("tokens_in_mean"),
                            f("tokens_out_mean"),
                            f("wall_s_mean")
                        );
                    }
                    println!("{v}");
                    0
                })
            })
        }
        Cmd::Batch { episodes, opts, fleet, .. } => {
            let library = (opts.skills == "use").then(|| opts.library());
            opts.episode_opts().and_then(|o| {
                match fleet::Backend::from_args(fleet.ray.as_deref(), fleet.workers) {
                    None => session::batch(&o, episodes, |i, r| match r {
                        Ok(r) => {
                            eprintln!("r2g batch: episode {i}: success {} in {} responses", r.success, r.responses);
                            if let Some(lib) = &library {
                                let lo = skills::learn::LearnOpts::new(lib.clone(), "scripted");
                                if let Err(e) = skills::learn::record_use(lib, std::path::Path::new(&r.run_dir), &lo) {
                                    eprintln!("r2g batch: episode {i}: the skills' use was not recorded: {e:#}");
                                }
                            }
                        }
                        Err(e) => eprintln!("r2g batch: episode {i}: {e:#}"),
                    }),
                    Some(b) => session::batch_on(&o, episodes, &b, |i, r| match r.get("error") {
                        Some(e) => eprintln!("r2g batch: episode {i}: {}", e.as_str().unwrap_or("failed")),
                        None => {
                            eprintln!(
                                "r2g batch: episode {i}: success {} in {} responses",
                                r["success"], r["responses"]
                            )
                        }
                    }),
                }
                .map(|v| {
                    println!("{v}");
                    // Failed tasks are results; a batch none of whose episodes could run at all (the
                    // endpoint or the gym failing every time) is a failure of the batch.
                    let ran_none = v["episodes"].as_u64().is_some_and(|n| n > 0) && v["errors"] == v["episodes"];
                    i32::from(ran_none)
                })
            })
        }
        Cmd::View { run_dir } => agent_host::viewer::write(&run_dir).map(|p| {
            println!("{}", p.display());
            0
        }),
        Cmd::Exec { file, instance, budget, wall_s, cpu_s, observe_only, scratch, memory, robot_config } => {
            let o = session::ExecOpts { instance, budget, wall_s, cpu_s, observe_only, scratch, memory, robot_config };
            session::exec(&file, &o).map(|v| {
                println!("{v}");
                0
            })
        }
        Cmd::Gyms => gyms(),
        Cmd::Service { which } => service::run(which),
        Cmd::Replay { gyms, placement, seeds, fleet, do_nothing, out } => {
            let backend = fleet::Backend::from_args(fleet.ray.as_deref(), fleet.workers);
            match (gyms.as_slice(), backend, seeds) {
                ([gym], None, None) if gym != "all" => replay(gym, &placement, do_nothing, &out),
                (_, _, _) if placement.perturb.is_some() => Err(anyhow::anyhow!(
                    "--perturb applies to one replay (one gym, --seed N); give no --seeds, --workers or --ray with it"
                )),
                (_, backend, seeds) => {
                    let gyms = if gyms.iter().any(|g| g == "all") { launch::gym_names() } else { gyms };
                    let backend = backend.unwrap_or(fleet::Backend::Local(1));
                    std::path::absolute(&out)
                        .map_err(anyhow::Error::from)
                        .and_then(|out| fleet::replays(&gyms, seeds.unwrap_or(1), &backend, &out))
                        .map(|v| {
                            println!("{v}");
                            i32::from(v["success_rate"].as_f64() != Some(1.0))
                        })
                }
            }
        }
        Cmd::AuthorDemo { gym } => author_demo(&gym),
        Cmd::Import { which } => import(which),
        Cmd::Augment { gym, candidates, seed, out, jobs, shrink_tries, no_sheet, factors, levels, fleet } => (|| {
            let mut o = real2sim::augment::Options::new(std::path::absolute(&out)?);
            o.candidates = candidates;
            o.seed = seed;
            o.jobs = jobs;
            if let Some(backend) = fleet::Backend::from_args(fleet.ray.as_deref(), fleet.workers) {
                // Each candidate a job; as many in flight as workers were asked for. On Ray
                // without --workers, a whole round at once: one driver submits every candidate
                // of the round as a task, and the cluster's `r2g_gym` slots decide how many run.
                let ray = matches!(backend, fleet::Backend::Ray { .. });
                // At most 64 threads: each also builds its candidate here (an IK re-solve).
                o.jobs = fleet.workers.unwrap_or(if ray { candidates.max(jobs).clamp(4, 64) } else { jobs.max(4) });
                o.validator = fleet_validator(backend);
            }
            o.shrink_tries = shrink_tries;
            o.sheet = !no_sheet;
            o.max_levels = levels.unwrap_or(usize::MAX);
            if !factors.is_empty() {
                o.factors = factors
                    .iter()
                    .map(|f| {
                        real2sim::augment::FACTORS.iter().copied().find(|k| k.name() == f).ok_or_else(|| {
                            anyhow::anyhow!(
                                "--factors: unknown factor '{f}' (accepted: {})",
                                real2sim::augment::FACTORS.map(|k| k.name()).join(", ")
                            )
                        })
                    })
                    .collect::<anyhow::Result<_>>()?;
            }
            augment(&gym, o)
        })(
        ),
        Cmd::Validate { gym, seed, out, keep_trace } => validate(&gym, seed, out, keep_trace),
        Cmd::Blender(a) => blender_cmd::run(a),
        Cmd::Render(a) => render_cmd::run(a),
        Cmd::Reconstruct(a) => reconstruct_cmd::run(a),
        Cmd::Compare(a) => compare_cmd::run(a),
        Cmd::Judge(a) => judge_cmd::run(a),
        Cmd::Bench { which: BenchCmd::Sim { gyms, frames } } => bench::sim::run(&gyms, frames).map(|_| 0),
        Cmd::Bench { which: BenchCmd::Skills { gyms, seeds, first_seed, perturb, jobs, out } } => {
            let o = bench::skills::Options { gyms, seeds, first_seed, perturb: perturb.to_string(), jobs, out };
            bench::skills::run(&o).map(|_| 0)
        }
        Cmd::Kin { which: KinCmd::Fk { args } } => kin::run(false, &args.robot, &args.tcp, args.frame.as_deref()),
        Cmd::Kin { which: KinCmd::Ik { args } } => kin::run(true, &args.robot, &args.tcp, args.frame.as_deref()),
        Cmd::Bench { which: BenchCmd::Ik { targets, count } } => bench::ik::run(targets.as_deref(), count).map(|_| 0),
        Cmd::Bench { which: BenchCmd::Tick { seconds, gym } } => bench::tick::run(&gym, seconds, false).map(|_| 0),
        Cmd::Bench { which: BenchCmd::Jitter { seconds, gym } } => bench::tick::run(&gym, seconds, true).map(|_| 0),
        Cmd::Bench { which: BenchCmd::Robo { samples, gym } } => bench::robo::run(&gym, samples).map(|_| 0),
        Cmd::Bench { which: BenchCmd::Agent { episodes } } => bench::agent::run(episodes).map(|_| 0),
        Cmd::Bench { which: BenchCmd::Perception { gyms, no_lift } } => {
            bench::perception::run(&gyms, !no_lift).map(|_| 0)
        }
        Cmd::Bench { which: BenchCmd::All { jitter_seconds, out, quick } } => {
            bench::all::run(jitter_seconds, &out, quick).map(|_| 0)
        }
        Cmd::Bench { which: BenchCmd::TickCompute { ticks } } => bench::control::tick_compute(ticks).map(|_| 0),
        Cmd::Bench { which: BenchCmd::Accept { seconds, only } } => {
            bench::accept::run(seconds, only.as_deref()).map(|_| 0)
        }
        Cmd::Bench { which: BenchCmd::Fci { lenient_peer } } => bench::fci::run(lenient_peer).map(|_| 0),
        Cmd::Bench { which: BenchCmd::LimiterFuzz { chunks, seed } } => {
            bench::control::limiter_fuzz(chunks, seed).map(|v| if v["violations"] == 0 { 0 } else { 1 })
        }
        Cmd::Bench { which: BenchCmd::Soak { minutes, gym, stall_s, sample_s } } => {
            bench::soak::run(&bench::soak::Options { minutes, gym, stall_s, sample_s }).map(|_| 0)
        }
        Cmd::Bench { which: BenchCmd::Batch { workers, replays, agents } } => {
            bench::batch::run(workers, replays, agents).map(|_| 0)
        }
        Cmd::Bench { which: BenchCmd::Ipc { only } } => bench::ipc::run(only.as_deref()).map(|_| 0),
        Cmd::Bench { which: BenchCmd::IpcPeer { transport, payload, addr, cpu } } => (|| {
            bench::ipc::peer(
                bench::ipc::Transport::parse(&transport)?,
                bench::ipc::Payload::parse(&payload)?,
                &addr,
                cpu,
            )
        })()
        .map(|_| 0),
    };
    match r {
        Ok(code) => std::process::exit(code),
        Err(e) => {
            eprintln!("r2g: error: {e:#}");
            std::process::exit(1);
        }
    }
}

fn gyms() -> anyhow::Result<i32> {
    let names = launch::gym_names();
    if names.is_empty() {
        anyhow::bail!("no gyms found in {}", launch::gyms_dir().display());
    }
    for n in names {
        println!("{n}");
    }
    Ok(0)
}

fn replay(gym: &str, placement: &PlacementArgs, do_nothing: bool, out: &std::path::Path) -> anyhow::Result<i32> {
    placement.check()?;
    let scene = launch::resolve_scene(gym)?;
    let r =
        lockstep::episode::replay_perturbed(&scene, placement.seed, placement.perturb.clone(), do_nothing, Some(out))?;
    for (row, why) in &r.failures {
        eprintln!("r2g replay: chunk from row {row} did not execute: {why}");
    }
    for (name, c) in &r.evaluation.checks {
        eprintln!("  {} {name}: {}", if c.pass { "pass" } else { "FAIL" }, c.value);
    }
    if let Some(p) = &r.trace_path {
        eprintln!("trace: {}", p.display());
    }
    println!("{}", serde_json::to_string(&r.evaluation)?);
    Ok(if r.evaluation.success { 0 } else { 1 })
}

fn import(which: ImportCmd) -> anyhow::Result<i32> {
    let done = match which {
        ImportCmd::Droid { episode, scene, out, fk_gate_m, fk_gate_rad } => real2sim::import::droid(
            &episode,
            &launch::resolve_scene(&scene)?,
            &out,
            real2sim::droid::FkGate { position_m: fk_gate_m, rotation_rad: fk_gate_rad },
        )?,
        ImportCmd::Egodex { episode, scene, out, hand, registration, min_confidence } => real2sim::import::egodex(
            &episode,
            &launch::resolve_scene(&scene)?,
            &out,
            &hand,
            registration.as_deref(),
            real2sim::retarget::HandParams { min_confidence, ..Default::default() },
        )?,
    };
    eprintln!("r2g import: wrote {} ({} rows)", done.dir.display(), done.rows);
    let mut line = done.report;
    line["gym"] = serde_json::json!(done.dir.display().to_string());
    println!("{line}");
    Ok(0)
}

/// Augmentation's gate as fleet jobs: `r2g validate <variant> --out <variant>` on a worker or
/// a Ray task, its evidence.json read back. On Ray one driver serves the whole augmentation
/// (started with the first candidate): the candidates validated at once run as tasks side by
/// side.
fn fleet_validator(backend: fleet::Backend) -> real2sim::augment::Validator {
    let pool: std::sync::Arc<std::sync::OnceLock<Result<fleet::Pool, String>>> = Default::default();
    std::sync::Arc::new(move |dir: &std::path::Path| {
        // Absolute: the job runs wherever a worker is, in whatever directory it has.
        let dir =
            &std::path::absolute(dir).map_err(|source| real2sim::Error::Io { path: dir.to_path_buf(), source })?;
        let args = vec!["validate".to_string(), dir.display().to_string(), "--out".into(), dir.display().to_string()];
        let mut failure = None;
        let mut check = |r: serde_json::Value| {
            if r["value"].is_null() {
                failure = Some(format!("the validation job failed: {}", r.get("error").unwrap_or(&r["stderr_tail"])));
            }
        };
        if matches!(backend, fleet::Backend::Ray { .. }) {
            let pool = pool.get_or_init(|| fleet::Pool::new(&backend).map_err(|e| format!("{e:#}")));
            let pool = pool.as_ref().map_err(|e| anyhow::anyhow!("{e}"))?;
            check(pool.run(args)?);
        } else {
            fleet::run(&[fleet::Job { id: 0, args }], &backend, dir, check)?;
        }
        let ev = std::fs::read_to_string(dir.join("evidence.json")).map_err(|e| {
            anyhow::anyhow!(
                "{}: no evidence.json ({e}){}",
                dir.display(),
                failure.map(|f| format!("; {f}")).unwrap_or_default()
            )
        })?;
        let ev: serde_json::Value = serde_json::from_str(&ev).map_err(anyhow::Error::from)?;
        Ok(real2sim::augment::Verdict::from_evidence(&ev))
    })
}

fn augment(gym: &str, o: real2sim::augment::Options) -> anyhow::Result<i32> {
    let scene = launch::resolve_scene(gym)?;
    let r = real2sim::augment::augment(&scene, &o, &|m: &str| eprintln!("r2g augment: {m}"))?;
    eprintln!("single-factor sweeps (feasible range per parameter):");
    for (k, v) in &r.feasible {
        eprintln!("  {k:<16} [{:.3}, {:.3}]", v[0], v[1]);
    }
    eprintln!("{} combined candidates, per factor:", r.candidates);
    for (f, c) in &r.per_factor {
        eprintln!("  {f:<16} {c:?}");
    }
    eprintln!(
        "kept {} variants ({} near-duplicates removed); {:.1} validated candidates per minute; {} gate runs in {:.0} s",
        r.kept.len(),
        r.deduplicated.len(),
        r.validated_per_minute,
        r.gate_runs,
        r.wall_s
    );
    let line = serde_json::json!({
        "parent": r.parent, "pool": o.out.display().to_string(), "candidates": r.candidates, "kept": r.kept.len(),
        "deduplicated": r.deduplicated.len(), "dropped": r.dropped.len(), "feasible": r.feasible, "per_factor": r.per_factor,
        "validated_per_minute": r.validated_per_minute, "gate_runs": r.gate_runs, "wall_s": r.wall_s,
        "contact_sheet": r.contact_sheet, "fleet_drivers_started": fleet::drivers_started(),
        "fleet_nodes": fleet::nodes_seen(),
    });
    println!("{line}");
    Ok(0)
}

fn validate(gym: &str, seed: u64, out: Option<std::path::PathBuf>, keep_trace: bool) -> anyhow::Result<i32> {
    let scene = launch::resolve_scene(gym)?;
    let name = scene.parent().and_then(|p| p.file_name()).map(|n| n.to_string_lossy().into_owned()).unwrap_or_default();
    let out = out.unwrap_or_else(|| std::path::Path::new("runs/validate").join(&name));
    let mut opts = real2sim::validate::Options::new(out);
    opts.seed = seed;
    opts.keep_trace = keep_trace;
    let (ev, path) = real2sim::validate::validate(&scene, &opts)?;
    for (name, c) in &ev.checks {
        eprintln!("  {} {name}: {}", if c.pass { "pass" } else { "FAIL" }, c.value);
    }
    println!("{}", ev.line(&path));
    Ok(if ev.success { 0 } else { 1 })
}

fn author_demo(gym: &str) -> anyhow::Result<i32> {
    let d = lockstep::author_demo(&launch::resolve_scene(gym)?)?;
    println!("wrote {} rows ({:.1} s at {} Hz) to {}", d.rows, d.rows as f64 / d.hz, d.hz, d.path.display());
    Ok(0)
}

#[allow(clippy::too_many_arguments)]
fn up(
    gym: &str,
    mode: ModeArg,
    instance: &str,
    render_hz: f64,
    sim_args: Vec<String>,
    robot_config: std::path::PathBuf,
    control_args: Vec<String>,
    side: &launch::RobotSide,
    placement: &PlacementArgs,
) -> anyhow::Result<i32> {
    placement.check()?;
    let mut sim_args = sim_args;
    sim_args.extend(placement.sim_args());
    let opts = UpOptions {
        scene: launch::resolve_scene(gym)?,
        instance: instance.into(),
        mode: match mode {
            ModeArg::Wall => Mode::Wall,
            ModeArg::Lockstep => Mode::Lockstep,
        },
        render_hz,
        control_args,
        sim_args,
        robot_config: Some(robot_config),
        ready_timeout: Duration::from_secs(60),
    };
    let mut inst = Instance::up_with(&opts, side)?;
    // Only once the instance is up (a second `up` of a running instance is refused before this),
    // so the file always names the `r2g up` that runs it.
    let pid_file = launch::up_pid_file(instance);
    write_pid_file(&pid_file)?;
    println!("READY {instance}");
    std::io::stdout().flush()?;
    let supervised = inst.supervise();
    let rc = match supervised {
        Ok(None) => {
            inst.stop();
            eprintln!("r2g: instance '{instance}' stopped");
            Ok(0)
        }
        Ok(Some(what)) => {
            eprintln!("r2g: {what}; stopping instance '{instance}'");
            inst.stop();
            Ok(1)
        }
        Err(e) => Err(e),
    };
    // Gone with the instance (its processes have exited and the last verdict is written).
    if std::fs::read_to_string(&pid_file).is_ok_and(|p| p.trim() == std::process::id().to_string()) {
        let _ = std::fs::remove_file(&pid_file);
    }
    rc
}

/// Writes this process's pid to `path` (write, then rename: never half written).
fn write_pid_file(path: &std::path::Path) -> anyhow::Result<()> {
    use anyhow::Context as _;
    if let Some(dir) = path.parent() {
        std::fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))?;
    }
    let tmp = path.with_extension(format!("pid.{}.partial", std::process::id()));
    std::fs::write(&tmp, format!("{}\n", std::process::id()))
        .and_then(|_| std::fs::rename(&tmp, path))
        .with_context(|| format!("writing {}", path.display()))
}

/// The command line of process `pid` (NUL-separated arguments), if it exists.
fn cmdline(pid: i32) -> Option<Vec<String>> {
    let raw = std::fs::read(format!("/proc/{pid}/cmdline")).ok()?;
    Some(raw.split(|&b| b == 0).filter(|a| !a.is_empty()).map(|a| String::from_utf8_lossy(a).into_owned()).collect())
}

/// Whether `pid` has exited (gone, or a zombie its parent has not reaped yet).
fn exited(pid: i32) -> bool {
    match std::fs::read_to_string(format!("/proc/{pid}/stat")) {
        // The state follows the command name in parentheses, which may itself hold ')'.
        Ok(stat) => stat.rsplit_once(')').is_some_and(|(_, rest)| rest.trim_start().starts_with(['Z', 'X'])),
        Err(_) => true,
    }
}

/// `r2g down`: SIGTERM to the `r2g up` of `instance` (checked by its command line, so a pid
/// reused by another process is never signalled), then wait until it has exited.
fn down(instance: &str, timeout_s: f64) -> anyhow::Result<i32> {
    if !(timeout_s.is_finite() && timeout_s > 0.0) {
        anyhow::bail!("--timeout-s must be a positive number of seconds");
    }
    let file = launch::up_pid_file(instance);
    let Ok(text) = std::fs::read_to_string(&file) else {
        eprintln!("r2g down: no `r2g up` of instance '{instance}' runs here (no {})", file.display());
        return Ok(1);
    };
    let Ok(pid) = text.trim().parse::<i32>() else {
        anyhow::bail!("{} holds {:?}, not a pid", file.display(), text.trim());
    };
    let is_ours = cmdline(pid).is_some_and(|args| {
        let up = args.iter().skip(1).any(|a| a == "up");
        let named = args.windows(2).any(|w| w[0] == "--instance" && w[1] == instance)
            || args.iter().any(|a| a == &format!("--instance={instance}"))
            || (instance == "default" && !args.iter().any(|a| a.starts_with("--instance")));
        up && named && args.first().is_some_and(|a| a.ends_with("r2g"))
    });
    if exited(pid) || !is_ours {
        eprintln!(
            "r2g down: {} names pid {pid}, which is not a running `r2g up --instance {instance}` (a stale file); \
             nothing was signalled",
            file.display()
        );
        return Ok(1);
    }
    // SAFETY: signals the process the pid file names, checked above to be that instance's `r2g up`.
    if unsafe { libc::kill(pid, libc::SIGTERM) } != 0 {
        anyhow::bail!("signalling pid {pid}: {}", std::io::Error::last_os_error());
    }
    let t0 = std::time::Instant::now();
    while !exited(pid) {
        if t0.elapsed().as_secs_f64() > timeout_s {
            eprintln!(
                "r2g down: `r2g up` (pid {pid}) of instance '{instance}' is still running after {timeout_s:.0} s"
            );
            return Ok(1);
        }
        std::thread::sleep(Duration::from_millis(20));
    }
    eprintln!("r2g down: instance '{instance}' stopped (r2g up, pid {pid}, has exited)");
    Ok(0)
}
