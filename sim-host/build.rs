// Binaries and tests of this crate find libmujoco at run time where they were linked against
// it (the pinned wheel in .venv, see .cargo/config.toml), with no LD_LIBRARY_PATH step.
fn main() {
    println!("cargo::rerun-if-env-changed=MUJOCO_DYNAMIC_LINK_DIR");
    if let Ok(dir) = std::env::var("MUJOCO_DYNAMIC_LINK_DIR") {
        println!("cargo::rustc-link-arg=-Wl,-rpath,{dir}");
    }
}
