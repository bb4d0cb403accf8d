// The wheel's native module finds libmujoco in the `mujoco` wheel installed beside it
// (site-packages/mujoco/libmujoco.so.X), never in the project's venv: a user's own venv has no
// such venv. `r2g_gym/__init__.py` also imports `mujoco` first, which loads that very library.
fn main() {
    println!("cargo::rustc-link-arg-cdylib=-Wl,-rpath,$ORIGIN/../mujoco");
}
