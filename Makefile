# Two commands: `make demo` and `make test`. Each installs what a fresh Debian machine lacks.
SHELL := /bin/bash
VENV := .venv
STAMPS := .stamps
export MUJOCO_GL := egl

.PHONY: demo test deps venv build robo bench-tick clean

demo: robo
	scripts/demo.sh

test: robo
	scripts/test.sh

deps: $(STAMPS)/deps
$(STAMPS)/deps: scripts/install-deps.sh
	scripts/install-deps.sh
	@mkdir -p $(STAMPS) && touch $@

venv: $(STAMPS)/venv
$(STAMPS)/venv: requirements.txt scripts/setup-venv.sh $(STAMPS)/deps
	scripts/setup-venv.sh
	@mkdir -p $(STAMPS) && touch $@

# Cargo decides what is stale; this always asks it.
build: venv
	cargo build --release --workspace --locked

robo: build
	PYO3_BUILD_EXTENSION_MODULE=1 VIRTUAL_ENV=$(CURDIR)/$(VENV) PATH=$(CURDIR)/$(VENV)/bin:$$PATH \
	  $(VENV)/bin/maturin develop --release --locked -q -m agent-host/Cargo.toml

bench-tick: build
	target/release/r2g bench tick --seconds 10

clean:
	rm -rf target $(VENV) $(STAMPS) demo-out
