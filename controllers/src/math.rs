//! Small rigid-transform helpers on plain arrays: quaternions are `[x, y, z, w]`, matrices are
//! row-major 3×3 (MuJoCo's layout). Enough for frames at the process boundary; the kinematics
//! of the Controllers issue will bring nalgebra.

pub type Quat = [f64; 4];
pub type Mat3 = [f64; 9];

pub fn quat_from_mat(m: &Mat3) -> Quat {
    let (m00, m01, m02, m10, m11, m12, m20, m21, m22) = (m[0], m[1], m[2], m[3], m[4], m[5], m[6], m[7], m[8]);
    let tr = m00 + m11 + m22;
    let q = if tr > 0.0 {
        let s = (tr + 1.0).sqrt() * 2.0;
        [(m21 - m12) / s, (m02 - m20) / s, (m10 - m01) / s, 0.25 * s]
    } else if m00 > m11 && m00 > m22 {
        let s = (1.0 + m00 - m11 - m22).sqrt() * 2.0;
        [0.25 * s, (m01 + m10) / s, (m02 + m20) / s, (m21 - m12) / s]
    } else if m11 > m22 {
        let s = (1.0 + m11 - m00 - m22).sqrt() * 2.0;
        [(m01 + m10) / s, 0.25 * s, (m12 + m21) / s, (m02 - m20) / s]
    } else {
        let s = (1.0 + m22 - m00 - m11).sqrt() * 2.0;
        [(m02 + m20) / s, (m12 + m21) / s, 0.25 * s, (m10 - m01) / s]
    };
    normalize(q)
}

pub fn normalize(q: Quat) -> Quat {
    let n = (q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3]).sqrt();
    if n > 0.0 {
        [q[0] / n, q[1] / n, q[2] / n, q[3] / n]
    } else {
        [0.0, 0.0, 0.0, 1.0]
    }
}

pub fn mul(a: Quat, b: Quat) -> Quat {
    let [ax, ay, az, aw] = a;
    let [bx, by, bz, bw] = b;
    [
        aw * bx + ax * bw + ay * bz - az * by,
        aw * by - ax * bz + ay * bw + az * bx,
        aw * bz + ax * by - ay * bx + az * bw,
        aw * bw - ax * bx - ay * by - az * bz,
    ]
}

pub fn conj(q: Quat) -> Quat {
    [-q[0], -q[1], -q[2], q[3]]
}

pub fn rotate(q: Quat, v: [f64; 3]) -> [f64; 3] {
    let p = mul(mul(q, [v[0], v[1], v[2], 0.0]), conj(q));
    [p[0], p[1], p[2]]
}

/// `a_from_c = a_from_b ∘ b_from_c` for poses given as (translation, rotation).
pub fn compose(a_from_b: ([f64; 3], Quat), b_from_c: ([f64; 3], Quat)) -> ([f64; 3], Quat) {
    let t = rotate(a_from_b.1, b_from_c.0);
    ([a_from_b.0[0] + t[0], a_from_b.0[1] + t[1], a_from_b.0[2] + t[2]], normalize(mul(a_from_b.1, b_from_c.1)))
}

pub fn inverse(a_from_b: ([f64; 3], Quat)) -> ([f64; 3], Quat) {
    let qi = conj(a_from_b.1);
    let t = rotate(qi, a_from_b.0);
    ([-t[0], -t[1], -t[2]], qi)
}

/// Axis-angle vector (axis × angle, angle in [0, π]) of a unit quaternion.
pub fn axis_angle(q: Quat) -> [f64; 3] {
    let q = normalize(q);
    // Same rotation, w ≥ 0, so the angle stays within [0, π].
    let q = if q[3] < 0.0 { [-q[0], -q[1], -q[2], -q[3]] } else { q };
    let s = (q[0] * q[0] + q[1] * q[1] + q[2] * q[2]).sqrt();
    if s < 1e-12 {
        return [0.0; 3];
    }
    let angle = 2.0 * s.atan2(q[3]);
    [q[0] / s * angle, q[1] / s * angle, q[2] / s * angle]
}

/// The axis-angle vector of `q` nearest `near`: the same rotation, its angle taken as θ, θ − 2π
/// or θ + 2π along the same axis. Reported poses stay continuous this way: a rotation of π about
/// x does not jump between [π, 0, 0] and [−π, 0, 0] from one report to the next.
pub fn axis_angle_near(q: Quat, near: [f64; 3]) -> [f64; 3] {
    let r = axis_angle(q);
    let angle = (r[0] * r[0] + r[1] * r[1] + r[2] * r[2]).sqrt();
    if angle < 1e-12 {
        return r;
    }
    let mut best = r;
    let mut best_d = f64::INFINITY;
    for k in [-1.0, 0.0, 1.0] {
        let scale = (angle + 2.0 * std::f64::consts::PI * k) / angle;
        let c = [r[0] * scale, r[1] * scale, r[2] * scale];
        let d = (0..3).map(|i| (c[i] - near[i]).powi(2)).sum::<f64>();
        if d < best_d {
            best_d = d;
            best = c;
        }
    }
    best
}

/// Row-major 4×4 homogeneous matrix of a pose.
pub fn homogeneous(p: [f64; 3], q: Quat) -> [[f64; 4]; 4] {
    let x = rotate(q, [1.0, 0.0, 0.0]);
    let y = rotate(q, [0.0, 1.0, 0.0]);
    let z = rotate(q, [0.0, 0.0, 1.0]);
    [[x[0], y[0], z[0], p[0]], [x[1], y[1], z[1], p[1]], [x[2], y[2], z[2], p[2]], [0.0, 0.0, 0.0, 1.0]]
}

#[cfg(test)]
mod tests {
    use super::*;

    fn close(a: &[f64], b: &[f64]) -> bool {
        a.iter().zip(b).all(|(x, y)| (x - y).abs() < 1e-9)
    }

    #[test]
    fn matrix_round_trip_in_every_branch() {
        for q in [
            [0.0, 0.0, 0.0, 1.0],
            [1.0, 0.0, 0.0, 0.0],
            [0.0, 1.0, 0.0, 0.0],
            [0.0, 0.0, 1.0, 0.0],
            normalize([0.3, -0.2, 0.5, 0.7]),
        ] {
            let h = homogeneous([0.0; 3], q);
            let m = [h[0][0], h[0][1], h[0][2], h[1][0], h[1][1], h[1][2], h[2][0], h[2][1], h[2][2]];
            let back = quat_from_mat(&m);
            let same = close(&back, &q) || close(&back, &[-q[0], -q[1], -q[2], -q[3]]);
            assert!(same, "{q:?} -> {back:?}");
        }
    }

    #[test]
    fn axis_angle_of_half_turn_about_x() {
        let aa = axis_angle([1.0, 0.0, 0.0, 0.0]);
        assert!(close(&aa, &[std::f64::consts::PI, 0.0, 0.0]));
    }

    #[test]
    fn compose_then_inverse_is_identity() {
        let a = ([0.1, -0.2, 0.3], normalize([0.1, 0.2, 0.3, 0.9]));
        let (p, q) = compose(a, inverse(a));
        assert!(close(&p, &[0.0; 3]));
        assert!(close(&q, &[0.0, 0.0, 0.0, 1.0]) || close(&q, &[0.0, 0.0, 0.0, -1.0]));
    }

    #[test]
    fn axis_angle_near_keeps_reports_continuous() {
        let pi = std::f64::consts::PI;
        // π about x, with w a hair on either side of zero: the same rotation both times.
        let a = [1.0, 0.0, 0.0, 1e-17];
        let b = [-1.0, 0.0, 0.0, 1e-17];
        let ra = axis_angle_near(a, [pi, 0.0, 0.0]);
        let rb = axis_angle_near(b, [pi, 0.0, 0.0]);
        assert!(close(&ra, &[pi, 0.0, 0.0]) && close(&rb, &[pi, 0.0, 0.0]), "{ra:?} {rb:?}");
        // Past π the report keeps growing instead of flipping sign.
        let past = normalize([(0.5 * (pi + 0.1)).sin(), 0.0, 0.0, (0.5 * (pi + 0.1)).cos()]);
        let r = axis_angle_near(past, [pi, 0.0, 0.0]);
        assert!(close(&r, &[pi + 0.1, 0.0, 0.0]), "{r:?}");
        // Small rotations are left alone.
        let small = normalize([0.0, 0.0, (0.05f64).sin(), (0.05f64).cos()]);
        assert!(close(&axis_angle_near(small, [0.0; 3]), &axis_angle(small)));
    }
}
