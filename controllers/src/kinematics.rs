//! Forward kinematics and geometric Jacobians of a serial chain read from URDF.
//!
//! The chain is stored as one fixed transform before each revolute joint (fixed URDF joints
//! between two arm joints are folded into it) plus a unit axis; every link reachable from the
//! root without passing a movable joint off the chain is a named frame. All poses are in the
//! frame of the URDF root link (the robot base). Nothing here allocates after construction.
#![allow(clippy::needless_range_loop)] // joint i indexes origins, axes, q and frames alike

use std::collections::HashMap;

use nalgebra::{Isometry3, SMatrix, Translation3, Unit, UnitQuaternion, Vector3};

use crate::error::Error;
use crate::N;

/// Rows 0–2: linear velocity of the frame origin; rows 3–5: angular velocity; base frame.
pub type Jacobian = SMatrix<f64, 6, N>;

/// A named frame fixed to one link of the chain.
#[derive(Debug, Clone)]
pub struct Frame {
    pub name: String,
    /// Arm joints that move this frame: joints `0..moved_by`.
    pub moved_by: usize,
    /// Pose in the frame of joint `moved_by - 1` after its rotation (or in the base when 0).
    offset: Isometry3<f64>,
}

/// Index of a frame in [`Kinematics::frames`].
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct FrameId(pub usize);

#[derive(Debug, Clone)]
pub struct Kinematics {
    origins: [Isometry3<f64>; N],
    axes: [Unit<Vector3<f64>>; N],
    frames: Vec<Frame>,
    by_name: HashMap<String, FrameId>,
    pub tcp: FrameId,
    /// The last link fixed to joint 7 before any tool: the flange.
    pub flange: FrameId,
}

fn isometry(o: &urdf_rs::Pose) -> Isometry3<f64> {
    let [x, y, z] = *o.xyz;
    let [r, p, yaw] = *o.rpy;
    Isometry3::from_parts(Translation3::new(x, y, z), UnitQuaternion::from_euler_angles(r, p, yaw))
}

impl Kinematics {
    /// Builds the chain from the URDF root to `tcp_link`. `arm_joints` are the chain's revolute
    /// joints in order (as found by [`crate::RobotModel`]).
    pub fn from_urdf(robot: &urdf_rs::Robot, tcp_link: &str, arm_joints: &[String; N]) -> Result<Self, Error> {
        let by_child: HashMap<&str, &urdf_rs::Joint> =
            robot.joints.iter().map(|j| (j.child.link.as_str(), j)).collect();
        let root = robot
            .links
            .iter()
            .map(|l| l.name.as_str())
            .find(|l| !by_child.contains_key(l))
            .ok_or_else(|| Error::Urdf("the URDF has no root link".into()))?;
        let mut origins = [Isometry3::identity(); N];
        let mut axes = [Vector3::z_axis(); N];
        let mut frames = vec![Frame { name: root.to_string(), moved_by: 0, offset: Isometry3::identity() }];
        // Walk down from the root: fixed joints accumulate, the next arm joint takes the sum.
        let mut stack = vec![(root, 0usize, Isometry3::identity())];
        while let Some((link, moved_by, offset)) = stack.pop() {
            for j in robot.joints.iter().filter(|j| j.parent.link == link) {
                let pose = offset * isometry(&j.origin);
                let child = j.child.link.as_str();
                match j.joint_type {
                    urdf_rs::JointType::Fixed => {
                        frames.push(Frame { name: child.to_string(), moved_by, offset: pose });
                        stack.push((child, moved_by, pose));
                    }
                    urdf_rs::JointType::Revolute if moved_by < N && arm_joints[moved_by] == j.name => {
                        let a = Vector3::new(j.axis.xyz[0], j.axis.xyz[1], j.axis.xyz[2]);
                        if !(a.norm() > 1e-9 && a.iter().all(|v| v.is_finite())) {
                            return Err(Error::BadLimit { joint: j.name.clone(), detail: "axis is zero".into() });
                        }
                        origins[moved_by] = pose;
                        axes[moved_by] = Unit::new_normalize(a);
                        frames.push(Frame {
                            name: child.to_string(),
                            moved_by: moved_by + 1,
                            offset: Isometry3::identity(),
                        });
                        stack.push((child, moved_by + 1, Isometry3::identity()));
                    }
                    // Grippers and anything else movable off the arm: not a fixed frame.
                    _ => {}
                }
            }
        }
        let mut by_name: HashMap<String, FrameId> =
            frames.iter().enumerate().map(|(i, f)| (f.name.clone(), FrameId(i))).collect();
        let tcp = *by_name.get(tcp_link).ok_or_else(|| Error::NoSuchLink {
            link: tcp_link.into(),
            known: frames.iter().map(|f| f.name.as_str()).collect::<Vec<_>>().join(", "),
        })?;
        if frames[tcp.0].moved_by != N {
            return Err(Error::WrongDof { link: tcp_link.into(), found: frames[tcp.0].moved_by });
        }
        // The flange: the fixed frame on joint 7 nearest to it (first one listed after the link).
        let flange = frames
            .iter()
            .position(|f| f.moved_by == N && f.offset.translation.vector.norm() > 0.0)
            .map(FrameId)
            .unwrap_or(tcp);
        by_name.entry("tcp".into()).or_insert(tcp);
        by_name.entry("flange".into()).or_insert(flange);
        Ok(Self { origins, axes, frames, by_name, tcp, flange })
    }

    /// The TCP's pose in the flange frame.
    pub fn flange_from_tcp(&self) -> Isometry3<f64> {
        self.offset(self.flange).inverse() * self.offset(self.tcp)
    }

    /// Makes the frame `flange_from_tcp` beyond the flange the TCP (a measured tool transform
    /// instead of the description's TCP link). The description's frames stay as they are; the
    /// new frame is named `tcp`. Everything that uses [`Self::tcp`] (FK, Jacobians, IK, the
    /// workspace check) follows it.
    pub fn set_tcp(&mut self, flange_from_tcp: Isometry3<f64>) -> Result<(), Error> {
        let flange = &self.frames[self.flange.0];
        if self.flange == self.tcp || flange.moved_by != N {
            return Err(Error::Urdf(format!(
                "no flange frame fixed to joint 7 before the TCP '{}': a flange-to-TCP transform cannot be applied",
                self.frames[self.tcp.0].name
            )));
        }
        let frame = Frame { name: "tcp".into(), moved_by: N, offset: flange.offset * flange_from_tcp };
        self.tcp = FrameId(self.frames.len());
        self.frames.push(frame);
        self.by_name.insert("tcp".into(), self.tcp);
        Ok(())
    }

    pub fn frames(&self) -> &[Frame] {
        &self.frames
    }

    pub fn frame(&self, name: &str) -> Option<FrameId> {
        self.by_name.get(name).copied()
    }

    /// Offset of `frame` from the frame of the last joint that moves it.
    pub fn offset(&self, frame: FrameId) -> Isometry3<f64> {
        self.frames[frame.0].offset
    }

    /// Poses of every joint frame (after its rotation) for configuration `q`.
    #[inline]
    pub fn joint_frames(&self, q: &[f64; N]) -> [Isometry3<f64>; N] {
        let mut out = [Isometry3::identity(); N];
        let mut t = Isometry3::identity();
        for i in 0..N {
            t = t * self.origins[i] * UnitQuaternion::from_axis_angle(&self.axes[i], q[i]);
            out[i] = t;
        }
        out
    }

    /// Pose of `frame` in the base frame.
    #[inline]
    pub fn fk(&self, q: &[f64; N], frame: FrameId) -> Isometry3<f64> {
        let f = &self.frames[frame.0];
        let mut t = Isometry3::identity();
        for ((origin, axis), qi) in self.origins.iter().zip(&self.axes).zip(q).take(f.moved_by) {
            t = t * origin * UnitQuaternion::from_axis_angle(axis, *qi);
        }
        t * f.offset
    }

    /// Pose of `frame` and its geometric Jacobian, both in the base frame.
    #[inline]
    pub fn jacobian(&self, q: &[f64; N], frame: FrameId) -> (Isometry3<f64>, Jacobian) {
        let joints = self.joint_frames(q);
        self.jacobian_from(&joints, frame)
    }

    /// As [`Self::jacobian`], from joint frames already computed.
    #[inline]
    pub fn jacobian_from(&self, joints: &[Isometry3<f64>; N], frame: FrameId) -> (Isometry3<f64>, Jacobian) {
        let f = &self.frames[frame.0];
        let pose = if f.moved_by == 0 { f.offset } else { joints[f.moved_by - 1] * f.offset };
        let p = pose.translation.vector;
        let mut jac = Jacobian::zeros();
        for (i, (joint, axis)) in joints.iter().zip(&self.axes).enumerate().take(f.moved_by) {
            let z = joint.rotation * axis.into_inner();
            let lin = z.cross(&(p - joint.translation.vector));
            jac.fixed_view_mut::<3, 1>(0, i).copy_from(&lin);
            jac.fixed_view_mut::<3, 1>(3, i).copy_from(&z);
        }
        (pose, jac)
    }
}

/// Position and `[x, y, z, w]` quaternion of an isometry, as plain arrays for the boundary.
pub fn to_arrays(t: &Isometry3<f64>) -> ([f64; 3], [f64; 4]) {
    let v = t.translation.vector;
    let q = t.rotation.quaternion();
    ([v.x, v.y, v.z], [q.i, q.j, q.k, q.w])
}

/// The isometry of a position and `[x, y, z, w]` quaternion (normalised here).
pub fn from_arrays(p: [f64; 3], q: [f64; 4]) -> Isometry3<f64> {
    Isometry3::from_parts(
        Translation3::new(p[0], p[1], p[2]),
        UnitQuaternion::from_quaternion(nalgebra::Quaternion::new(q[3], q[0], q[1], q[2])),
    )
}
