//! `r2g bench sim`: how fast physics runs in lockstep with the controller, per gym, and how long
//! a 640×480 frame takes to render, RGB alone and RGB-D.
pub fn run(_g: &[String], _f: usize) -> anyhow::Result<()> {
    anyhow::bail!("todo")
}
