//! The build shares compilations: the release binaries (`cargo build --workspace`), the `robo`
//! extension (`maturin develop`, which builds that package alone) and the test binaries (which
//! add the dev-dependencies) must resolve every dependency with the same features, or Cargo
//! compiles it, and everything above it, once more. The pins that keep it so are in
//! `robo/Cargo.toml`; these tests compare the graphs with `cargo tree` and name what to pin.

use std::collections::BTreeSet;
use std::process::Command;

/// `name version features` of every package in the graph `args` selects.
fn graph(args: &[&str]) -> BTreeSet<String> {
    let cargo = std::env::var("CARGO").unwrap_or_else(|_| "cargo".into());
    let out = Command::new(cargo)
        .current_dir(integration_tests::root())
        .arg("tree")
        .args(args)
        .args(["--format", "{p} {f}", "--prefix", "none", "--offline", "--locked"])
        .output()
        .expect("running cargo tree");
    assert!(out.status.success(), "cargo tree {args:?} failed: {}", String::from_utf8_lossy(&out.stderr));
    String::from_utf8_lossy(&out.stdout)
        .lines()
        .map(|l| l.trim_end_matches(" (*)").trim_end().to_string())
        .filter(|l| !l.is_empty())
        .collect()
}

/// `name version` of a graph line.
fn package(line: &str) -> String {
    line.split_whitespace().take(2).collect::<Vec<_>>().join(" ")
}

#[test]
fn dev_dependencies_change_no_features_of_the_release_graph() {
    let release = graph(&["--workspace", "-e", "normal,build"]);
    let with_dev = graph(&["--workspace", "-e", "normal,build,dev"]);
    let packages: BTreeSet<String> = release.iter().map(|l| package(l)).collect();
    let changed: Vec<&String> = with_dev.difference(&release).filter(|l| packages.contains(&package(l))).collect();
    assert!(
        changed.is_empty(),
        "the dev-dependencies give these packages other features than `cargo build --workspace` does, so \
         `cargo test` would compile them (and everything above them) again; pin these features in \
         robo/Cargo.toml or trim the dev-dependency's features: {changed:#?}"
    );
}

#[test]
fn the_extension_alone_resolves_like_the_workspace() {
    let workspace = graph(&["--workspace", "-e", "normal,build"]);
    // robo, and the gymnasium environment's module, which maturin builds alone too.
    let differ: Vec<String> = ["robo", "r2g-gym"]
        .iter()
        .flat_map(|ext| {
            let alone = graph(&["-p", ext, "-e", "normal,build"]);
            let workspace = &workspace;
            alone
                .difference(workspace)
                .map(|l| {
                    let theirs: Vec<&String> = workspace.iter().filter(|w| package(w) == package(l)).collect();
                    format!("{ext} alone: {l}; the workspace: {theirs:?}")
                })
                .collect::<Vec<_>>()
        })
        .collect();
    assert!(
        differ.is_empty(),
        "`maturin develop` (robo alone) would resolve these packages with other features than the \
         workspace build, and compile them again; pin the workspace's features in robo/Cargo.toml: \
         {differ:#?}"
    );
}
