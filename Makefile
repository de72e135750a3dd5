# One task runner, used by CI and by people alike.
PYTHON ?= python3
VENV   ?= .venv
BIN    := $(VENV)/bin
# Stage commands in dvc.yaml call `python`: make it the venv's.
export PATH := $(abspath $(BIN)):$(PATH)

.PHONY: setup lock setup-system setup-node repro verify test test-team ci lint bench ui clean team-start team-stop team-status firmware

setup: $(VENV)/.installed

# Installs from requirements.lock (every package pinned, with its sha256; `make lock` writes it) with
# uv, in seconds. The lock names the CPU build of torch (2.13.0+cpu) by version and hash, not by place:
# WHEELS is where that wheel is found (this machine's folder by default; a lab without it gives the
# PyTorch CPU index, docs/reproducibility.md "Installing"). --compile-bytecode: where PYTHONDONTWRITEBYTECODE
# is set (this project's machines), nothing would ever write the libraries' bytecode, and every process
# would compile torch, pandas and MLflow again: 16 s instead of 7 s to import them here.
UV_VERSION := 0.13.9
WHEELS ?= $(if $(wildcard /opt/wheels/torch-*),--find-links /opt/wheels,--extra-index-url https://download.pytorch.org/whl/cpu)
UV := $(BIN)/uv
# The lock holds every third-party package; the project's two distributions, the simulator's client
# (client/, docs/client.md) and the training package that depends on it, are installed from their folders.
$(VENV)/.installed: pyproject.toml client/pyproject.toml requirements.lock
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --disable-pip-version-check uv==$(UV_VERSION)
	$(UV) pip install --quiet --python $(BIN)/python --compile-bytecode --require-hashes $(WHEELS) -r requirements.lock
	$(UV) pip install --quiet --python $(BIN)/python --no-deps -e ./client -e .
	touch $@

# Rewrites requirements.lock from pyproject.toml's dependencies and extras, keeping every pin the lock
# already has unless pyproject.toml rules it out (`make lock UPGRADE=--upgrade` takes the newest). The
# client's own dependencies come in through needlecue-client (client/pyproject.toml), which is not locked.
lock: $(VENV)/.installed
	$(UV) pip compile --quiet pyproject.toml --extra dev --extra team --generate-hashes \
	  --python-version 3.11 --python-platform x86_64-manylinux_2_28 $(WHEELS) $(UPGRADE) \
	  --custom-compile-command "make lock" --no-emit-package needlecue-client --output-file requirements.lock

# PostgreSQL's server, for the team stack; Chromium, for the trainee page's browser test; the AVR
# toolchain, the Arduino core and simavr, for the firmware and its emulated board (Debian's packages;
# needs root). Nothing if they are there.
AVR_PACKAGES := gcc-avr avr-libc arduino-core-avr libsimavr-dev libelf-dev pkg-config
setup-system:
	@ls /usr/lib/postgresql/*/bin/pg_ctl >/dev/null 2>&1 || command -v pg_ctl >/dev/null || \
	  { apt-get update -q && DEBIAN_FRONTEND=noninteractive apt-get install -y -q postgresql; }
	@command -v chromium >/dev/null || \
	  { apt-get update -q && DEBIAN_FRONTEND=noninteractive apt-get install -y -q chromium; }
	@dpkg -s $(AVR_PACKAGES) >/dev/null 2>&1 || \
	  { apt-get update -q && DEBIAN_FRONTEND=noninteractive apt-get install -y -q $(AVR_PACKAGES); }
	@command -v systemd-analyze >/dev/null || \
	  { apt-get update -q && DEBIAN_FRONTEND=noninteractive apt-get install -y -q systemd; }
	@command -v npm >/dev/null || \
	  { apt-get update -q && DEBIAN_FRONTEND=noninteractive apt-get install -y -q nodejs npm; }

# The JavaScript client of deploy/node (onnxruntime for Node.js, pinned by its package-lock.json);
# --ignore-scripts: the package ships its CPU runtime, its install script only fetches CUDA's.
setup-node: deploy/node/node_modules/.installed

deploy/node/node_modules/.installed: deploy/node/package.json deploy/node/package-lock.json
	cd deploy/node && npm ci --ignore-scripts --no-audit --no-fund --loglevel=error
	touch $@

firmware: setup-system  ## the estimator's firmware (firmware/build/needlecue.hex, to flash) and its emulated board
	$(MAKE) -C firmware hex board

team-start: setup setup-system  ## the team stack: PostgreSQL, S3 (SeaweedFS), MLflow with basic auth (docs/team.md)
	$(BIN)/needlecue team start
team-stop: setup
	$(BIN)/needlecue team stop
team-status: setup
	$(BIN)/needlecue team status

repro: setup          ## install, then run the whole pipeline on the built-in simulated rig (dvc repro's stages, on every core)
	$(BIN)/needlecue repro

verify: repro         ## the pipeline, then: nothing out of date; dvc.lock and metrics.json byte for byte the committed ones
	$(BIN)/dvc status --quiet || { $(BIN)/dvc status; echo "verify: dvc status: stages out of date"; exit 1; }
	git diff --exit-code --stat -- dvc.lock reports/metrics.json || { echo "verify: this machine wrote another dvc.lock (docs/reproducibility.md)"; exit 1; }

test: setup setup-system setup-node  ## lint and run the test suite, the team stack's included (on both cores; its tests on one)
	$(BIN)/ruff check .
	$(BIN)/pytest -q -n 2 --dist loadgroup

test-team: setup setup-system  ## only the tests against the real team stack (tests/team/)
	$(BIN)/pytest -q -m team

# `make verify` (the whole pipeline, 8 to 13 min) is not part of CI, which should stay under 30 min: the suite
# checks that dvc.lock belongs to the committed code and params (tests/test_dvc_lock.py), and whoever
# changes a stage runs `make verify` and commits the lock it writes.
ci: test              ## what CI runs (.ci/run, on a fresh clone): the README's test command

lint: setup
	$(BIN)/ruff check .
	$(BIN)/ruff format --check .

# The README's timings come from one run of it (docs/reproducibility.md): bench_newcomer clones HEAD afresh
# and times the install (an empty uv cache), make repro and make test there (about 25 min of the whole).
bench: repro          ## dvc repro timings (cold per stage, no-op, retrain), throughput, the peer comparison, the client's latency, a fresh clone's install, make repro and make test
	$(BIN)/python benchmarks/bench_pipeline.py
	$(BIN)/python benchmarks/bench_data.py
	$(BIN)/python benchmarks/bench_peer.py
	$(BIN)/python benchmarks/bench_client.py
	$(BIN)/python benchmarks/bench_deployed.py
	$(BIN)/python benchmarks/bench_newcomer.py

ui: setup             ## the MLflow UI on the runs of every angle and kind, best first (prints the link)
	$(BIN)/needlecue ui --port $${PORT:-5000}

clean:                ## generated data and reports (never data/raw)
	rm -rf data/simulated data/interim data/processed data/predictions reports/ingest reports/resample
