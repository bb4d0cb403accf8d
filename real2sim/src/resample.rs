//! Resampling a source's frames (DROID 15 Hz, EgoDex 30 Hz) onto the demonstration's rate
//! (20 Hz). Values between two frames are interpolated, except across a gripper switch: a row
//! that falls between two frames of different gripper state takes the nearer frame whole, so no
//! row ever holds a half-open gripper the source never commanded, and each switch lands on the
//! row nearest its source time (at most half a row away; the exact source times are kept in
//! `events.json`).

/// How one output row is made: `(1 − w)·frame[a] + w·frame[b]`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Blend {
    pub a: usize,
    pub b: usize,
    pub w: f64,
}

/// Rows at `hz` from `t_s[0]` to the last frame's time. `state[k]` is the gripper state of
/// frame k (true: closed).
pub fn plan(t_s: &[f64], state: &[bool], hz: f64) -> Vec<Blend> {
    let (Some(&t0), Some(&t1)) = (t_s.first(), t_s.last()) else { return Vec::new() };
    let rows = ((t1 - t0) * hz).round() as usize + 1;
    let mut out = Vec::with_capacity(rows);
    let mut k = 0;
    for r in 0..rows {
        let t = (t0 + r as f64 / hz).min(t1);
        while k + 1 < t_s.len() && t_s[k + 1] < t {
            k += 1;
        }
        if k + 1 >= t_s.len() {
            out.push(Blend { a: k, b: k, w: 0.0 });
            continue;
        }
        let w = ((t - t_s[k]) / (t_s[k + 1] - t_s[k])).clamp(0.0, 1.0);
        if state.get(k) != state.get(k + 1) {
            let nearest = if w < 0.5 { k } else { k + 1 };
            out.push(Blend { a: nearest, b: nearest, w: 0.0 });
        } else {
            out.push(Blend { a: k, b: k + 1, w });
        }
    }
    out
}

/// Applies a plan to rows of numbers (linear interpolation).
pub fn apply<const N: usize>(plan: &[Blend], frames: &[[f64; N]]) -> Vec<[f64; N]> {
    plan.iter().map(|b| std::array::from_fn(|j| (1.0 - b.w) * frames[b.a][j] + b.w * frames[b.b][j])).collect()
}

/// Two-level hysteresis: true once a value rises above `on`, false again once it falls below
/// `off` (`off < on`); the first frame is true when it is above the midpoint.
pub fn hysteresis(values: &[f64], on: f64, off: f64) -> Vec<bool> {
    let mut state = values.first().is_some_and(|v| *v > 0.5 * (on + off));
    values
        .iter()
        .map(|&v| {
            if state && v < off {
                state = false;
            } else if !state && v > on {
                state = true;
            }
            state
        })
        .collect()
}

/// Removes runs of a state shorter than `min_s` (hysteresis in time): such a run takes the state
/// of the run before it.
pub fn debounce(state: &[bool], t_s: &[f64], min_s: f64) -> Vec<bool> {
    let mut out = state.to_vec();
    let mut start = 0;
    while start < out.len() {
        let mut end = start;
        while end + 1 < out.len() && out[end + 1] == out[start] {
            end += 1;
        }
        let next_t = t_s.get(end + 1).copied().unwrap_or(f64::INFINITY);
        if start > 0 && end + 1 < out.len() && next_t - t_s[start] < min_s {
            let prev = out[start - 1];
            out[start..=end].iter_mut().for_each(|s| *s = prev);
            // The run merged into its predecessor; look again from where that run began.
            start = out[..start].iter().rposition(|s| *s != prev).map(|i| i + 1).unwrap_or(0);
            continue;
        }
        start = end + 1;
    }
    out
}

/// Times of the state changes: (time halfway between the two frames, new state).
pub fn switches(state: &[bool], t_s: &[f64]) -> Vec<(f64, bool)> {
    (1..state.len()).filter(|&k| state[k] != state[k - 1]).map(|k| (0.5 * (t_s[k - 1] + t_s[k]), state[k])).collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn rows_between_frames_of_one_state_interpolate_and_a_switch_is_never_blended() {
        let t: Vec<f64> = (0..16).map(|k| k as f64 / 15.0).collect();
        let state: Vec<bool> = (0..16).map(|k| k >= 7).collect();
        let values: Vec<[f64; 1]> = (0..16).map(|k| [if k >= 7 { 1.0 } else { -1.0 }]).collect();
        let p = plan(&t, &state, 20.0);
        assert_eq!(p.len(), 21);
        let out = apply(&p, &values);
        assert!(out.iter().all(|v| v[0] == 1.0 || v[0] == -1.0), "{out:?}");
        // The switch (between frames 6 and 7, at 0.433 s) lands on the row nearest it.
        let first_closed = out.iter().position(|v| v[0] == 1.0).expect("closes");
        assert!((first_closed as f64 / 20.0 - 0.433).abs() <= 0.5 / 20.0 + 0.5 / 15.0, "{first_closed}");
        // Inside one state, values interpolate: a ramp stays a ramp.
        let ramp: Vec<[f64; 1]> = t.iter().map(|&x| [x]).collect();
        let r = apply(&plan(&t, &[false; 16], 20.0), &ramp);
        assert!(r.iter().enumerate().all(|(i, v)| (v[0] - i as f64 / 20.0).abs() < 1e-12));
    }

    #[test]
    fn hysteresis_and_debounce_ignore_chatter() {
        let v = [0.0, 0.45, 0.55, 0.65, 0.5, 0.45, 0.3, 0.7];
        assert_eq!(hysteresis(&v, 0.6, 0.4), [false, false, false, true, true, true, false, true]);
        let t: Vec<f64> = (0..10).map(|k| k as f64 * 0.1).collect();
        let s = [false, false, true, false, false, true, true, true, true, true];
        // The lone `true` at 0.2 s lasts 0.1 s: gone with a 0.15 s minimum.
        assert_eq!(debounce(&s, &t, 0.15), [false, false, false, false, false, true, true, true, true, true]);
        assert_eq!(switches(&debounce(&s, &t, 0.15), &t), vec![(0.45, true)]);
    }
}
