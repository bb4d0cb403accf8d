//! The physics side: a compiled scene, one step per command sample, reset to the scene's
//! initial state, and the measured robot state a real arm would report.

use std::sync::Arc;

use controllers::math;
use controllers::RobotModel;
use ipc_schema::{JointCommand, Pose, SimState, N_JOINTS};
use mujoco_rs::mujoco_c::{mj_contactForce, mj_forward, mj_resetData};
use mujoco_rs::prelude::*;

use crate::mjcf;
use crate::placement::{symmetric, turn_about_z, Perturbation, PerturbationError, Placed, CLEARANCE_M, REACH_M, TRIES};
use crate::scene::Scene;
use crate::trace::{Sample, Trace};

#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum SimError {
    #[error(transparent)]
    Scene(#[from] crate::scene::SceneError),
    #[error("robot model: {0}")]
    Robot(#[from] controllers::Error),
    // Not a `source`: the message already holds it, and a chain printed with `{:#}` would say it twice.
    #[error("scene to MJCF: {0}")]
    Mjcf(mjcf::MjcfError),
    #[error("MuJoCo refused the compiled model: {0}")]
    Compile(String),
    #[error("compiled model lacks {0}")]
    Missing(String),
}

impl From<mjcf::MjcfError> for SimError {
    fn from(e: mjcf::MjcfError) -> Self {
        Self::Mjcf(e)
    }
}

/// Indices into the compiled model, resolved once.
#[derive(Debug, Clone)]
pub struct Layout {
    pub arm_qpos: [usize; N_JOINTS],
    pub arm_dof: [usize; N_JOINTS],
    pub finger_qpos: Vec<usize>,
    pub pos_act: [usize; N_JOINTS],
    pub vel_act: [usize; N_JOINTS],
    pub grip_act: usize,
    pub tcp_site: usize,
    pub base_body: usize,
    pub cameras: Vec<(String, usize)>,
    /// Per object: body id and the qpos address of its free joint (None when welded).
    pub objects: Vec<(usize, Option<usize>)>,
    /// Per fixture joint: fixture name, qpos address, and its start position (native units).
    pub fixture_joints: Vec<(String, usize, f64)>,
    /// Owner (index into [`Sim::owners`]) of every geom; u16::MAX for none.
    pub geom_owner: Vec<u16>,
    /// The owner id of the robot's geoms.
    pub robot_owner: u16,
}

pub struct Sim {
    pub scene: Scene,
    pub robot: RobotModel,
    pub mjcf: String,
    pub model: Arc<MjModel>,
    pub data: MjData<Arc<MjModel>>,
    pub layout: Layout,
    home_q: [f64; N_JOINTS],
    home_finger: f64,
    /// Commands computed from states older than this are stale (sent before a reset landed).
    pub reset_state_seq: u64,
    /// What can touch, for the trace: objects, fixtures, then table, robot, floor.
    pub owners: Vec<String>,
    /// Seed of the episode's augmentation (0: the scene exactly as written).
    pub seed: u64,
    /// Moves free objects further than their jitter at each reset with a non-zero seed.
    perturbation: Option<Perturbation>,
    /// Where the last reset's perturbation put the moved objects.
    pub placed: Option<Placed>,
    steps: u64,
}

/// Physics steps between two trace samples at the default 1 ms timestep (10 ms of sim time).
const TRACE_PERIOD_S: f64 = 0.01;

fn id(model: &MjModel, kind: MjtObjBase, name: &str) -> Result<usize, SimError> {
    model.name_to_id(kind, name).ok_or_else(|| SimError::Missing(format!("{kind:?} '{name}'")))
}

impl Sim {
    pub fn load(scene_path: &std::path::Path) -> Result<Self, SimError> {
        Self::from_scene(Scene::load(scene_path)?)
    }

    /// Compiles a scene already loaded (and checked: [`Scene::load`]); `r2g render` uses it to
    /// compile a gym with the cameras of a BOP `scene_camera.json` in place of its own.
    pub fn from_scene(scene: Scene) -> Result<Self, SimError> {
        let urdf = std::fs::read_to_string(&scene.robot.urdf)
            .map_err(|source| crate::scene::SceneError::Urdf { path: scene.robot.urdf.clone(), source })?;
        let robot = RobotModel::from_urdf_str(&urdf, &scene.robot.tcp_link, scene.robot.profile())?;
        let xml = mjcf::compile(&scene, &urdf, &robot)?;
        let model = Arc::new(MjModel::from_xml_string(&xml).map_err(|e| SimError::Compile(format!("{e}")))?);
        let m: &MjModel = &model;
        let joint = |n: &str| id(m, MjtObjBase::mjOBJ_JOINT, n);
        let mut layout = Layout {
            arm_qpos: [0; N_JOINTS],
            arm_dof: [0; N_JOINTS],
            finger_qpos: Vec::new(),
            pos_act: [0; N_JOINTS],
            vel_act: [0; N_JOINTS],
            grip_act: id(m, MjtObjBase::mjOBJ_ACTUATOR, mjcf::GRIPPER_ACTUATOR)?,
            tcp_site: id(m, MjtObjBase::mjOBJ_SITE, mjcf::TCP_SITE)?,
            base_body: 0,
            cameras: Vec::new(),
            objects: Vec::new(),
            fixture_joints: Vec::new(),
            geom_owner: Vec::new(),
            robot_owner: u16::MAX,
        };
        let f = m.ffi();
        // SAFETY: the address arrays hold njnt entries and the ids come from name lookups.
        let (qposadr, dofadr) = unsafe {
            (
                std::slice::from_raw_parts(f.jnt_qposadr, f.njnt as usize),
                std::slice::from_raw_parts(f.jnt_dofadr, f.njnt as usize),
            )
        };
        for (i, name) in robot.joint_names.iter().enumerate() {
            let j = joint(name)?;
            layout.arm_qpos[i] = qposadr[j] as usize;
            layout.arm_dof[i] = dofadr[j] as usize;
            layout.pos_act[i] = id(m, MjtObjBase::mjOBJ_ACTUATOR, &format!("{name}_pos"))?;
            layout.vel_act[i] = id(m, MjtObjBase::mjOBJ_ACTUATOR, &format!("{name}_vel"))?;
        }
        let urdf_robot = urdf_rs::read_from_string(&urdf).map_err(|e| SimError::Compile(e.to_string()))?;
        for j in urdf_robot.joints.iter().filter(|j| {
            j.name == robot.finger_joint || j.mimic.as_ref().is_some_and(|mm| mm.joint == robot.finger_joint)
        }) {
            layout.finger_qpos.push(qposadr[joint(&j.name)?] as usize);
        }
        let root = robot
            .joint_names
            .first()
            .and_then(|n| urdf_robot.joints.iter().find(|j| &j.name == n))
            .map(|j| j.parent.link.clone());
        layout.base_body = id(m, MjtObjBase::mjOBJ_BODY, &root.unwrap_or_default())?;
        for c in &scene.cameras {
            layout.cameras.push((c.name.clone(), id(m, MjtObjBase::mjOBJ_CAMERA, &c.name)?));
        }
        for o in &scene.objects {
            let body = id(m, MjtObjBase::mjOBJ_BODY, &o.name)?;
            let free = if o.free { Some(qposadr[joint(&format!("{}_free", o.name))?] as usize) } else { None };
            layout.objects.push((body, free));
        }
        for fx in scene.fixtures.iter() {
            if let Some(j) = &fx.joint {
                let jid = joint(&format!("{}{}", fx.name, mjcf::JOINT_SUFFIX))?;
                layout.fixture_joints.push((fx.name.clone(), qposadr[jid] as usize, j.initial_native()));
            }
        }
        // Owners: every body belongs to the top-level body under the world it hangs from.
        let mut owners: Vec<String> = scene.objects.iter().map(|o| o.name.clone()).collect();
        owners.extend(scene.fixtures.iter().map(|x| x.name.clone()));
        owners.extend(["table", "robot", "floor"].map(String::from));
        let owner_of_name = |n: &str| owners.iter().position(|o| o == n).map(|i| i as u16);
        // SAFETY: body_parentid holds nbody entries, geom_bodyid ngeom; names come from the model.
        let (parent, geom_body) = unsafe {
            (
                std::slice::from_raw_parts(f.body_parentid, f.nbody as usize),
                std::slice::from_raw_parts(f.geom_bodyid, f.ngeom as usize),
            )
        };
        let robot_owner = owner_of_name("robot").unwrap_or(u16::MAX);
        layout.robot_owner = robot_owner;
        let top_of = |b: usize| {
            let mut top = b;
            while top != 0 && parent[top] != 0 {
                top = parent[top] as usize;
            }
            top
        };
        // The robot's tree hangs from the URDF's root link, which need not be the link the
        // first joint moves from (a URDF may mount `link0` on a `world` or `base` link): every
        // geom under that root is the robot's, the arm's, the hand's and the fingers'.
        let robot_top = top_of(layout.base_body);
        for (g, &b) in geom_body.iter().enumerate() {
            let top = top_of(b as usize);
            let owner = if top == 0 {
                let name = m.id_to_name(MjtObjBase::mjOBJ_GEOM, g).unwrap_or_default();
                owner_of_name(name).unwrap_or(u16::MAX)
            } else if top == robot_top {
                robot_owner
            } else {
                let name = m.id_to_name(MjtObjBase::mjOBJ_BODY, top).unwrap_or_default();
                owner_of_name(name).unwrap_or(u16::MAX)
            };
            layout.geom_owner.push(owner);
        }
        let home_q = scene.robot.initial_joints_rad;
        let home_finger = robot.finger_from_gripper(scene.robot.initial_gripper);
        let data = MjData::new(model.clone());
        let mut sim = Self {
            scene,
            robot,
            mjcf: xml,
            model,
            data,
            layout,
            home_q,
            home_finger,
            reset_state_seq: 0,
            owners,
            seed: 0,
            perturbation: None,
            placed: None,
            steps: 0,
        };
        sim.reset();
        Ok(sim)
    }

    /// Restores the robot and every object to the scene's initial state.
    pub fn reset(&mut self) {
        // SAFETY: the live model/data pair of this Sim.
        unsafe { mj_resetData(self.model.ffi(), self.data.ffi_mut()) };
        let home_q = self.home_q;
        let finger = self.home_finger;
        let l = self.layout.clone();
        {
            let qpos = self.qpos_mut();
            for i in 0..N_JOINTS {
                qpos[l.arm_qpos[i]] = home_q[i];
            }
            for &a in &l.finger_qpos {
                qpos[a] = finger;
            }
            for (_, adr, initial) in &l.fixture_joints {
                qpos[*adr] = *initial;
            }
        }
        self.augment();
        self.steps = 0;
        let ctrl = self.ctrl_mut();
        for i in 0..N_JOINTS {
            ctrl[l.pos_act[i]] = home_q[i];
            ctrl[l.vel_act[i]] = 0.0;
        }
        ctrl[l.grip_act] = finger;
        // SAFETY: the model/data pair of this Sim, taken afresh after the borrows above ended.
        unsafe { mj_forward(self.model.ffi(), self.data.ffi_mut()) };
    }

    /// Moves objects by the episode seed (seed 0 leaves the scene as written): each object by
    /// its own `jitter_xy_m`/`jitter_yaw_deg`, and those the [`Perturbation`] names by its
    /// ranges instead, in a draw that keeps them clear of everything else ([`crate::placement`]).
    fn augment(&mut self) {
        self.placed = None;
        if self.seed == 0 {
            return;
        }
        let mut rng = controllers::ik::SplitMix64::new(self.seed);
        let moved = match &self.perturbation {
            Some(p) => p.moved(&self.scene).unwrap_or_default(),
            None => Vec::new(),
        };
        let specs: Vec<(f64, f64)> = self.scene.objects.iter().map(|o| (o.jitter_xy_m, o.jitter_yaw_deg)).collect();
        for (i, (xy, yaw)) in specs.into_iter().enumerate() {
            // Every object draws its jitter, so adding a perturbation changes no other draw.
            let (dx, dy, dyaw) =
                (symmetric(&mut rng) * xy, symmetric(&mut rng) * xy, (symmetric(&mut rng) * yaw).to_radians());
            if !moved.contains(&i) {
                self.offset_object(i, dx, dy, dyaw);
            }
        }
        let Some(p) = self.perturbation.clone() else { return };
        let start: Vec<f64> = self.qpos().to_vec();
        let mut placed = Placed::default();
        for attempt in 0..TRIES {
            for &i in &moved {
                let (dx, dy, dyaw) = (
                    symmetric(&mut rng) * p.xy_m,
                    symmetric(&mut rng) * p.xy_m,
                    (symmetric(&mut rng) * p.yaw_deg).to_radians(),
                );
                self.offset_object(i, dx, dy, dyaw);
            }
            if self.placement_fits(&moved) {
                placed.rejected = attempt;
                break;
            }
            self.qpos_mut().copy_from_slice(&start);
            if attempt + 1 == TRIES {
                placed.rejected = TRIES;
                placed.note = Some(format!(
                    "no placement within {p} kept {CLEARANCE_M} m from everything else in {TRIES} draws (seed {}): \
                     the written placement was kept",
                    self.seed
                ));
            }
        }
        let qpos = self.qpos();
        for &i in &moved {
            if let (o, Some(a)) = (&self.scene.objects[i], self.layout.objects[i].1) {
                placed.objects.push((
                    o.name.clone(),
                    [qpos[a], qpos[a + 1], qpos[a + 2]],
                    [qpos[a + 3], qpos[a + 4], qpos[a + 5], qpos[a + 6]],
                ));
            }
        }
        self.placed = Some(placed);
    }

    /// Moves object `i`'s start pose by (dx, dy) and turns it by `dyaw` about world z.
    fn offset_object(&mut self, i: usize, dx: f64, dy: f64, dyaw: f64) {
        let Some(a) = self.layout.objects[i].1 else { return };
        let qpos = self.qpos_mut();
        qpos[a] += dx;
        qpos[a + 1] += dy;
        let q = turn_about_z([qpos[a + 3], qpos[a + 4], qpos[a + 5], qpos[a + 6]], dyaw);
        qpos[a + 3..a + 7].copy_from_slice(&q);
    }

    /// Whether the `moved` objects, as qpos now places them, sit on the table within reach and
    /// keep [`CLEARANCE_M`] from every other collision geometry (the table and floor aside).
    fn placement_fits(&mut self, moved: &[usize]) -> bool {
        // SAFETY: the live model/data pair of this Sim; kinematics only (positions of geoms).
        unsafe { mujoco_rs::mujoco_c::mj_kinematics(self.model.ffi(), self.data.ffi_mut()) };
        let base = self.scene.robot.base_position_m;
        let qpos = self.qpos();
        for &i in moved {
            let Some(a) = self.layout.objects[i].1 else { continue };
            let (x, y) = (qpos[a], qpos[a + 1]);
            if let Some(t) = &self.scene.table {
                let c = t.top_center_m;
                if (x - c[0]).abs() > t.size_m[0] / 2.0 - CLEARANCE_M
                    || (y - c[1]).abs() > t.size_m[1] / 2.0 - CLEARANCE_M
                {
                    return false;
                }
            }
            if (x - base[0]).hypot(y - base[1]) > REACH_M {
                return false;
            }
        }
        let m = self.model.ffi();
        let ng = m.ngeom as usize;
        // SAFETY: contype/conaffinity hold ngeom entries.
        let (contype, conaff) = unsafe {
            (std::slice::from_raw_parts(m.geom_contype, ng), std::slice::from_raw_parts(m.geom_conaffinity, ng))
        };
        let owners = &self.layout.geom_owner;
        let moved_owner: Vec<u16> = moved.iter().map(|&i| i as u16).collect();
        let (table, floor) = (self.owner_id("table"), self.owner_id("floor"));
        let solid = |g: usize| contype[g] != 0 || conaff[g] != 0;
        for g1 in (0..ng).filter(|&g| solid(g) && moved_owner.contains(&owners[g])) {
            for g2 in (0..ng).filter(|&g| solid(g) && owners[g] != owners[g1]) {
                let o2 = owners[g2];
                // Each pair of moved objects once; the surfaces they stand on never count.
                if o2 == u16::MAX || Some(o2) == table || Some(o2) == floor || (moved_owner.contains(&o2) && g2 < g1) {
                    continue;
                }
                let mut fromto = [0.0f64; 6];
                // SAFETY: valid geom ids of this model; fromto is the 6-number buffer it fills.
                let d = unsafe {
                    mujoco_rs::mujoco_c::mj_geomDistance(
                        m,
                        self.data.ffi_mut(),
                        g1 as i32,
                        g2 as i32,
                        CLEARANCE_M,
                        &mut fromto,
                    )
                };
                if d < CLEARANCE_M {
                    return false;
                }
            }
        }
        true
    }

    fn owner_id(&self, name: &str) -> Option<u16> {
        self.owners.iter().position(|o| o == name).map(|i| i as u16)
    }

    /// Sets the placement perturbation applied at every reset with a non-zero seed (checked
    /// against the scene: named objects must exist and be free), and resets.
    pub fn set_perturbation(&mut self, p: Option<Perturbation>) -> Result<(), PerturbationError> {
        if let Some(p) = &p {
            p.moved(&self.scene)?;
        }
        self.perturbation = p;
        self.reset();
        Ok(())
    }

    /// Samples the trace when it is due (every 10 ms of simulated time, and at step 0).
    pub fn record(&self, trace: &mut Trace) {
        let every = ((TRACE_PERIOD_S / self.scene.timestep_s).round() as u64).max(1);
        if self.steps.is_multiple_of(every) {
            trace.samples.push(self.sample());
        }
    }

    /// An empty trace naming what this scene records.
    pub fn new_trace(&self) -> Trace {
        Trace {
            gym: self.scene.name.clone(),
            seed: self.seed,
            perturbation: self.perturbation.as_ref().map(|p| p.to_string()),
            owners: self.owners.clone(),
            objects: self.scene.objects.iter().map(|o| o.name.clone()).collect(),
            joints: self.layout.fixture_joints.iter().map(|j| j.0.clone()).collect(),
            finger_max_m: self.robot.finger_max_m,
            samples: Vec::new(),
        }
    }

    /// What the trace keeps of the present state.
    pub fn sample(&self) -> Sample {
        let d = self.data.ffi();
        let l = &self.layout;
        let qpos = self.qpos();
        // SAFETY: xpos/xquat hold nbody entries, site_xpos nsite; contact holds ncon entries.
        let (xpos, xquat, site, contacts) = unsafe {
            let nb = self.model.ffi().nbody as usize;
            (
                std::slice::from_raw_parts(d.xpos, 3 * nb),
                std::slice::from_raw_parts(d.xquat, 4 * nb),
                std::slice::from_raw_parts(d.site_xpos.add(3 * l.tcp_site), 3),
                std::slice::from_raw_parts(d.contact, d.ncon.max(0) as usize),
            )
        };
        let objects = l
            .objects
            .iter()
            .map(|&(b, _)| {
                [
                    xpos[3 * b],
                    xpos[3 * b + 1],
                    xpos[3 * b + 2],
                    xquat[4 * b],
                    xquat[4 * b + 1],
                    xquat[4 * b + 2],
                    xquat[4 * b + 3],
                ]
            })
            .collect();
        let joints = l
            .fixture_joints
            .iter()
            .zip(self.scene.fixtures.iter().filter_map(|f| f.joint.as_ref()))
            .map(|((_, adr, _), spec)| spec.to_spec_unit(qpos[*adr]))
            .collect();
        let mut pairs = Vec::new();
        let (mut pen, mut pen_pair) = (0.0f64, [u16::MAX; 2]);
        for c in contacts {
            let owner = |g: i32| l.geom_owner.get(g as usize).copied().unwrap_or(u16::MAX);
            let (a, b) = (owner(c.geom[0]), owner(c.geom[1]));
            if a == b || a == u16::MAX || b == u16::MAX || c.exclude != 0 {
                continue;
            }
            let pair = [a.min(b), a.max(b)];
            if c.dist < 0.0 {
                pairs.push(pair);
            }
            if -c.dist > pen {
                pen = -c.dist;
                pen_pair = pair;
            }
        }
        pairs.sort_unstable();
        pairs.dedup();
        Sample {
            t_s: d.time,
            objects,
            joints,
            tcp_m: [site[0], site[1], site[2]],
            finger_m: l.finger_qpos.first().map(|&a| qpos[a]).unwrap_or(0.0),
            arm_rad: l.arm_qpos.iter().map(|&a| qpos[a]).collect(),
            contacts: pairs,
            penetration_m: pen,
            penetration_pair: pen_pair,
        }
    }

    /// Poses the scene as a trace sample of this scene recorded it: free objects, fixture
    /// joints, the arm's joints and the fingers (velocities zero), then forward kinematics, so
    /// bodies, sites and cameras stand where they stood at `sample.t_s`. Welded objects never
    /// move and keep their pose. A sample without the arm's angles (a trace written before they
    /// were recorded) or of another scene's layout is refused.
    pub fn set_state_from_sample(&mut self, sample: &Sample) -> Result<(), String> {
        let l = self.layout.clone();
        if sample.objects.len() != l.objects.len() || sample.joints.len() != l.fixture_joints.len() {
            return Err(format!(
                "the trace sample at t = {} s holds {} objects and {} fixture joints; scene '{}' has {} and {}",
                sample.t_s,
                sample.objects.len(),
                sample.joints.len(),
                self.scene.name,
                l.objects.len(),
                l.fixture_joints.len()
            ));
        }
        if sample.arm_rad.len() != N_JOINTS {
            return Err(format!(
                "the trace sample at t = {} s has {} arm joint angles (arm_rad), {N_JOINTS} are needed: \
                 traces written before the arm's angles were recorded cannot pose the arm; record it again",
                sample.t_s,
                sample.arm_rad.len()
            ));
        }
        let all = sample.objects.iter().flatten().chain(&sample.joints).chain(&sample.arm_rad);
        if !all.chain([&sample.finger_m]).all(|v| v.is_finite()) {
            return Err(format!("the trace sample at t = {} s holds a number that is not finite", sample.t_s));
        }
        let natives: Vec<f64> = self
            .scene
            .fixtures
            .iter()
            .filter_map(|f| f.joint.as_ref())
            .zip(&sample.joints)
            .map(|(j, &v)| match j.kind {
                crate::scene::JointKind::Slide => v,
                crate::scene::JointKind::Hinge => v.to_radians(),
            })
            .collect();
        // SAFETY: the live model/data pair of this Sim.
        unsafe { mj_resetData(self.model.ffi(), self.data.ffi_mut()) };
        {
            let qpos = self.qpos_mut();
            for (o, &(_, free)) in sample.objects.iter().zip(&l.objects) {
                if let Some(a) = free {
                    qpos[a..a + 7].copy_from_slice(o);
                }
            }
            for ((_, adr, _), v) in l.fixture_joints.iter().zip(natives) {
                qpos[*adr] = v;
            }
            for (i, &a) in l.arm_qpos.iter().enumerate() {
                qpos[a] = sample.arm_rad[i];
            }
            for &a in &l.finger_qpos {
                qpos[a] = sample.finger_m;
            }
        }
        let ctrl = self.ctrl_mut();
        for i in 0..N_JOINTS {
            ctrl[l.pos_act[i]] = sample.arm_rad[i];
            ctrl[l.vel_act[i]] = 0.0;
        }
        ctrl[l.grip_act] = sample.finger_m;
        // SAFETY: the model/data pair of this Sim.
        unsafe {
            let d = self.data.ffi_mut();
            d.time = sample.t_s;
            mj_forward(self.model.ffi(), d);
        }
        Ok(())
    }

    fn slice_mut(&mut self, f: impl Fn(&mut mujoco_rs::mujoco_c::mjData) -> (*mut f64, usize)) -> &mut [f64] {
        // SAFETY: the pointer/length pairs come from mjData arrays sized by the model.
        unsafe {
            let (p, n) = f(self.data.ffi_mut());
            std::slice::from_raw_parts_mut(p, n)
        }
    }

    pub fn qpos_mut(&mut self) -> &mut [f64] {
        let nq = self.model.ffi().nq as usize;
        self.slice_mut(|d| (d.qpos, nq))
    }

    pub fn qpos(&self) -> &[f64] {
        // SAFETY: qpos holds nq values.
        unsafe { std::slice::from_raw_parts(self.data.ffi().qpos, self.model.ffi().nq as usize) }
    }

    fn ctrl_mut(&mut self) -> &mut [f64] {
        let nu = self.model.ffi().nu as usize;
        self.slice_mut(|d| (d.ctrl, nu))
    }

    /// Applies one command and advances physics by one timestep.
    pub fn step(&mut self, cmd: &JointCommand) {
        let l = self.layout.clone();
        let finger_max = self.robot.finger_max_m;
        let fresh = cmd.state_seq >= self.reset_state_seq;
        let ctrl = self.ctrl_mut();
        // Commands computed before the latest reset would yank the arm back: hold instead.
        if fresh {
            for i in 0..N_JOINTS {
                if cmd.q_rad[i].is_finite() && cmd.dq_rad_s[i].is_finite() {
                    ctrl[l.pos_act[i]] = cmd.q_rad[i];
                    ctrl[l.vel_act[i]] = cmd.dq_rad_s[i];
                }
            }
            if cmd.finger_m.is_finite() {
                ctrl[l.grip_act] = cmd.finger_m.clamp(0.0, finger_max);
            }
        }
        self.data.step();
        self.steps += 1;
    }

    pub fn time_s(&self) -> f64 {
        self.data.ffi().time
    }

    /// World pose of the robot base body.
    pub fn world_from_base(&self) -> ([f64; 3], math::Quat) {
        let d = self.data.ffi();
        let b = self.layout.base_body;
        // SAFETY: xpos/xquat hold nbody entries; base_body is a valid body id.
        unsafe {
            let p = std::slice::from_raw_parts(d.xpos.add(3 * b), 3);
            let q = std::slice::from_raw_parts(d.xquat.add(4 * b), 4);
            ([p[0], p[1], p[2]], [q[1], q[2], q[3], q[0]])
        }
    }

    /// The measured robot, in the robot base frame.
    pub fn measure(&self, seq: u64, command_seq: u64, reset_id: u64) -> SimState {
        let d = self.data.ffi();
        let l = &self.layout;
        let qpos = self.qpos();
        // SAFETY: qvel holds nv values; site arrays hold nsite entries.
        let (qvel, site_p, site_m) = unsafe {
            (
                std::slice::from_raw_parts(d.qvel, self.model.ffi().nv as usize),
                std::slice::from_raw_parts(d.site_xpos.add(3 * l.tcp_site), 3),
                std::slice::from_raw_parts(d.site_xmat.add(9 * l.tcp_site), 9),
            )
        };
        let mut s = SimState { seq, command_seq, reset_id, sim_time_s: d.time, ..Default::default() };
        for i in 0..N_JOINTS {
            s.q_rad[i] = qpos[l.arm_qpos[i]];
            s.dq_rad_s[i] = qvel[l.arm_dof[i]];
        }
        s.finger_m = l.finger_qpos.first().map(|&a| qpos[a]).unwrap_or(0.0);
        s.finger_max_m = self.robot.finger_max_m;
        let mut m = [0.0; 9];
        m.copy_from_slice(site_m);
        let world_from_tcp = ([site_p[0], site_p[1], site_p[2]], math::quat_from_mat(&m));
        let (p, q) = math::compose(math::inverse(self.world_from_base()), world_from_tcp);
        s.base_from_tcp = Pose { position_m: p, quat_xyzw: q };
        let (_, world_q) = self.world_from_base();
        s.external_force_n = math::rotate(math::conj(world_q), self.external_force_world());
        s
    }

    /// Net force of every active contact between the robot and anything else on the robot, in
    /// the world frame, N. Forces the robot exerts on itself cancel and are not counted.
    pub fn external_force_world(&self) -> [f64; 3] {
        let (m, d) = (self.model.ffi(), self.data.ffi());
        let l = &self.layout;
        // SAFETY: contact holds ncon entries.
        let contacts = unsafe { std::slice::from_raw_parts(d.contact, d.ncon.max(0) as usize) };
        let mut total = [0.0; 3];
        for (i, c) in contacts.iter().enumerate() {
            if c.exclude != 0 || c.efc_address < 0 {
                continue;
            }
            let owner = |g: i32| l.geom_owner.get(g as usize).copied().unwrap_or(u16::MAX);
            let (a, b) = (owner(c.geom[0]), owner(c.geom[1]));
            // The contact force acts on geom 1 along the frame's normal (from geom 0 to 1).
            let sign = match (a == l.robot_owner, b == l.robot_owner) {
                (false, true) => 1.0,
                (true, false) => -1.0,
                _ => continue,
            };
            let mut f = [0.0; 6];
            // SAFETY: i < ncon; f has the six entries the function writes.
            unsafe { mj_contactForce(m, d, i as i32, &mut f) };
            for (k, t) in total.iter_mut().enumerate() {
                *t += sign * (c.frame[k] * f[0] + c.frame[3 + k] * f[1] + c.frame[6 + k] * f[2]);
            }
        }
        total
    }
}
