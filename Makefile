# Two commands: `make demo` and `make test`. Each installs what a fresh Debian machine lacks.
SHELL := /bin/bash
VENV := .venv
STAMPS := .stamps
export MUJOCO_GL := egl

# One compilation of every dependency for the release binaries, the `robo` extension and the
# test binaries (`make test` builds each workspace crate once per profile, plus the cfg(test)
# builds of the crates themselves). Two things used to split them:
# - pyo3's build script reruns, and pyo3 and `robo` compile again, whenever PYO3_PYTHON,
#   PYO3_ENVIRONMENT_SIGNATURE or PYO3_BUILD_EXTENSION_MODULE differ from the last build;
#   maturin sets them for its build, so every cargo command here sees the same values (a
#   plain `cargo build` outside make does not, and costs the next make a pyo3 rebuild);
# - Cargo resolves features per invocation: `maturin develop` builds `robo` alone and
#   `cargo test` adds dev-dependencies. robo/Cargo.toml pins the workspace's features
#   (tests/tests/build.rs checks the graphs agree).
# The test binaries link no libpython either way: pyo3 finds no shared libpython here and
# `robo`'s own tests never call into Python.
export PYO3_PYTHON := $(CURDIR)/$(VENV)/bin/python
export PYO3_BUILD_EXTENSION_MODULE := 1
export PYO3_ENVIRONMENT_SIGNATURE = $(shell $(PYO3_PYTHON) -c 'import sys; v = sys.version_info; \
  print(f"{sys.implementation.name}-{v.major}.{v.minor}-{64 if sys.maxsize > 2**32 else 32}bit")' 2>/dev/null)

.PHONY: demo test deps venv build robo gym-wheel blender-env bench-tick clean

demo: robo blender-env
	scripts/demo.sh

test: robo gym-wheel blender-env
	scripts/test.sh

deps: $(STAMPS)/deps
$(STAMPS)/deps: scripts/install-deps.sh
	scripts/install-deps.sh
	@mkdir -p $(STAMPS) && touch $@

venv: $(STAMPS)/venv
$(STAMPS)/venv: requirements.txt requirements-ray.txt fci/franka-sim/requirements.txt scripts/setup-venv.sh $(STAMPS)/deps
	scripts/setup-venv.sh
	@mkdir -p $(STAMPS) && touch $@

# Cargo decides what is stale; this always asks it.
build: venv
	cargo build --release --workspace --locked

# The Python extensions: `robo` (agents), `r2g_camera` (the camera host's publisher) and `r2g_gym`
# (gymnasium environments).
robo: build
	VIRTUAL_ENV=$(CURDIR)/$(VENV) PATH=$(CURDIR)/$(VENV)/bin:$$PATH $(VENV)/bin/maturin develop --release --locked -m robo/Cargo.toml
	VIRTUAL_ENV=$(CURDIR)/$(VENV) PATH=$(CURDIR)/$(VENV)/bin:$$PATH $(VENV)/bin/maturin develop --release --locked -m camera-host/Cargo.toml
	VIRTUAL_ENV=$(CURDIR)/$(VENV) PATH=$(CURDIR)/$(VENV)/bin:$$PATH $(VENV)/bin/maturin develop --release --locked -m gym-env/Cargo.toml

# The r2g_gym wheel for users' own venvs, and a wheelhouse of its dependencies (the test that
# installs it into a fresh venv runs offline).
gym-wheel: robo
	scripts/gym-wheel.sh

# Blender as a Python module in .venv-blender (`r2g blender`, `r2g compare`): about 374 MB to
# download once; the script keeps its own stamp and returns at once when up to date.
blender-env: $(STAMPS)/deps
	scripts/setup-blender.sh

bench-tick: build
	target/release/r2g bench tick --seconds 10

clean:
	rm -rf target $(VENV) .venv-blender $(STAMPS) demo-out
