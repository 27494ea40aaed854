# The user's interface. Every target bootstraps .venv (Python >= 3.11, pinned packages) by itself.
PYTHON ?= python3
VENV := .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed
export MUJOCO_GL ?= egl
# XLA:CPU's multi-threaded Eigen pool can wedge on large vmapped MJX graphs (idle, never returns)
export XLA_FLAGS ?= --xla_cpu_multi_thread_eigen=false
OUT ?= runs/demo
EPISODES ?= 10

CONFIG ?= demo

.PHONY: setup demo test test-slow bench success-table data render-check train clean

$(STAMP): pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install -q --upgrade pip
	$(PY) -m pip install -q -e '.[dev]'
	touch $(STAMP)

setup: $(STAMP)

# Until the full demo chain exists: the scripted-policy success table, small and on the CPU.
demo: setup
	$(PY) -m sim_data.success_table --backend cpu --episodes $(EPISODES) --skills 0.2,0.6,1.0 --out $(OUT)/success_table.json

success-table: setup
	$(PY) -m sim_data.success_table --episodes 100 --skills 0.2,0.6,1.0 --out runs/success_table.json

data: setup
	$(PY) -m sim_data.generate --config $(CONFIG) --out $(if $(filter command line,$(origin OUT)),$(OUT),runs/data/$(CONFIG))

# make train CONFIG=demo DATA=runs/data/demo OUT=runs/wm/demo
train: setup
	$(PY) -m wm.train --config $(CONFIG) --data $(or $(DATA),runs/data/$(CONFIG)) --out $(if $(filter command line,$(origin OUT)),$(OUT),runs/wm/$(CONFIG))

render-check: setup
	$(PY) -m sim_data.render_check --states 50 --out runs/render_check.json

test: setup
	$(PY) -m pytest -q

test-slow: setup
	$(PY) -m pytest -q -m slow

bench: setup
	$(PY) -m sim_data.bench --out runs/bench/physics_$$(hostname).json
	$(PY) -m sim_data.bench_render --out runs/bench/render_$$(hostname).json
	$(PY) -m sim_data.bench_data --out runs/bench/data_$$(hostname).json
	$(PY) -m wm.bench --out runs/bench/wm_$$(hostname).json

clean:
	rm -rf runs/demo .pytest_cache
