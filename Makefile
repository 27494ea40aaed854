# The user's interface. Every target bootstraps .venv (Python >= 3.11, pinned packages) by itself.
PYTHON ?= python3
VENV := .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed
export MUJOCO_GL ?= egl
# XLA's flags of every command (sim_data.util.XLA_DEFAULT_FLAGS: XLA:CPU's Eigen pool off, a GPU's
# deterministic ops on), which importing sim_data also sets; named here so a user sees and can change them
export XLA_FLAGS ?= --xla_cpu_multi_thread_eigen=false --xla_gpu_deterministic_ops=true


CONFIG ?= demo

.PHONY: setup demo full test test-slow lint bench success-table data render-check train bundle policies eval report videos export-lerobot sweep clean

# uv installs the same pinned packages as pip in less time (27 s against 43 s on 2 cores); compiled to
# bytecode at install as pip does, since a PYTHONDONTWRITEBYTECODE environment never caches it on import
$(STAMP): pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install -q uv==0.13.9
	$(PY) -m uv pip install -q --compile-bytecode --python $(PY) -e '.[dev]'
	touch $(STAMP)

setup: $(STAMP)

# The whole chain at small scale on the CPU (data, policies, world model, evaluation, report); ends with the report's path.
demo: setup
	$(PY) -m experiments.pipeline demo

# The GPU preset in stages that each fit one 10-minute command and resume: make full STAGE=data|policies|rollouts|train|eval|report
# (ARGS="--minutes 9": every stage in order within a 9-minute slot; rerun to continue)
STAGE ?= all
full: setup
	$(PY) -m experiments.pipeline full --stage $(STAGE) $(ARGS)

success-table: setup
	$(PY) -m sim_data.bench.success_table --episodes 100 --skills 0.2,0.6,1.0 --out runs/success_table.json

data: setup
	$(PY) -m sim_data.dataset.generate --config $(CONFIG) --out $(if $(filter command line,$(origin OUT)),$(OUT),runs/data/$(CONFIG))

# make train CONFIG=demo DATA=runs/data/demo OUT=runs/wm/demo
train: setup
	$(PY) -m wm.train --config $(CONFIG) --data $(or $(DATA),runs/data/$(CONFIG)) --out $(if $(filter command line,$(origin OUT)),$(OUT),runs/wm/$(CONFIG))

# make bundle RUN=runs/wm/demo OUT=runs/bundles/demo: the trained model in files to copy to another machine
# (bfloat16 shards of <= 15 MiB, hashed); make eval ARGS="wm=runs/bundles/demo" loads it like a run
bundle: setup
	$(PY) -m wm.checkpoint $(or $(RUN),runs/wm/$(CONFIG)) $(or $(OUT),runs/bundles/$(CONFIG))

# make policies CONFIG=demo DATA=runs/data/demo OUT=runs/policies/demo
policies: setup
	$(PY) -m sim_data.policies.zoo --config $(CONFIG) --data $(or $(DATA),runs/data/$(CONFIG)) --out $(if $(filter command line,$(origin OUT)),$(OUT),runs/policies/$(CONFIG))

# make eval CONFIG=demo OUT=runs/eval/demo [ARGS="policies=runs/policies/demo,examples.plugin_policy:make wm=runs/wm/demo"]
eval: setup
	$(PY) -m experiments.evaluate --config $(CONFIG) --out $(if $(filter command line,$(origin OUT)),$(OUT),runs/eval/$(CONFIG)) $(ARGS)

# make report RUN=runs/eval/demo [SWEEPS=runs/sweeps: a section per sweep]
report: setup
	$(PY) -m experiments.report $(or $(RUN),runs/eval/$(CONFIG)) $(if $(SWEEPS),--sweeps $(SWEEPS))

# make videos RUN=runs/eval/demo: RUN/videos/*.mp4, real and imagined episodes side by side per policy, and the controllability panel
videos: setup
	$(PY) -m experiments.videos $(or $(RUN),runs/eval/$(CONFIG))

# make export-lerobot DATA=runs/data/demo OUT=runs/lerobot/demo: the dataset in LeRobot's layout v3.0
export-lerobot: setup
	$(PY) -m sim_data.dataset.lerobot $(or $(DATA),runs/data/$(CONFIG)) $(or $(OUT),runs/lerobot/$(CONFIG))

render-check: setup
	$(PY) -m sim_data.bench.render_check --states 50 --out runs/render_check.json

test: setup
	$(PY) -m pytest -q -n 2 --dist worksteal

test-slow: setup
	$(PY) -m pytest -q -m slow

# ruff with pyproject.toml's [tool.ruff]: unused or undefined names, the order of imports
lint: setup
	$(VENV)/bin/ruff check .

# make sweep SWEEP=data_scaling|task_scaling|... SIZE=demo|full OUT=runs/sweeps/<name>
# (SWEEP="a b c": several sharing the GPUs, into OUT/<name>)
SWEEP ?= data_scaling
SIZE ?= demo
sweep: setup
	$(PY) -m experiments.sweep $(SWEEP) --size $(SIZE) --out $(or $(OUT),$(if $(word 2,$(SWEEP)),runs/sweeps/$(SIZE),runs/sweeps/$(SWEEP)_$(SIZE)))

bench: setup
	$(PY) -m sim_data.bench.physics --out runs/bench/physics_$$(hostname).json
	$(PY) -m sim_data.bench.render --out runs/bench/render_$$(hostname).json
	$(PY) -m sim_data.bench.data --out runs/bench/data_$$(hostname).json
	$(PY) -m sim_data.bench.policy --out runs/bench/policy_$$(hostname).json
	$(PY) -m wm.bench --out runs/bench/wm_$$(hostname).json

clean:
	rm -rf runs/data/demo runs/policies/demo runs/wm/demo runs/wm/demo_seed* runs/bundles/demo runs/bundles/demo_seed* runs/eval/demo .pytest_cache
