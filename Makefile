# Two commands a new user needs: `make demo` and `make test`.
# Both create .venv once and reinstall only when pyproject.toml or constraints.txt change.
PYTHON ?= python3.11
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed

DOCS_STAMP := $(VENV)/.installed-docs
# The extras whose code paths the README claims are installed for the tests, so CI runs their tests
# instead of skipping them: SB3 zips and agents (sb3), the MuJoCo envs of Ch. 4-6 (mujoco), the Ray backend on
# a local instance the test session starts on 127.0.0.1 (ray). HYBRIDCTL_REQUIRE_EXTRAS makes a missing one an
# error at the start of the session (tests/conftest.py) instead of a quiet skip.
TEST_EXTRAS := test,sb3,mujoco,ray

.PHONY: demo test test-fast test-all bench docs venv clean

$(STAMP): pyproject.toml constraints.txt Makefile
	test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install -q --upgrade pip
	$(BIN)/python -m pip install -q -c constraints.txt -e ".[$(TEST_EXTRAS)]"
	touch $(STAMP)

$(DOCS_STAMP): $(STAMP)
	$(BIN)/python -m pip install -q -c constraints.txt -e ".[$(TEST_EXTRAS),docs]"
	touch $(DOCS_STAMP)

venv: $(STAMP)

demo: $(STAMP)
	$(BIN)/hybridctl demo --out runs/demo

# two test processes (pytest-xdist): CI's 2 cores; each test still uses one torch thread. --dist loadgroup keeps
# the tests marked xdist_group("ray") on one process, so the session starts one local Ray instance, not two.
test: $(STAMP)
	HYBRIDCTL_REQUIRE_EXTRAS=$(TEST_EXTRAS) $(BIN)/python -m pytest -q -n 2 --dist loadgroup

# The edit-test loop: the tests not marked slow or heavy (tests/conftest.py: HEAVY_FILES), aim under 90 s on 2 cores.
test-fast: $(STAMP)
	$(BIN)/python -m pytest -q -n 2 --dist loadgroup -m "not slow and not heavy"

# Everything, the slow tests too (the documentation build in headless Chromium among them).
test-all: $(DOCS_STAMP)
	HYBRIDCTL_REQUIRE_EXTRAS=$(TEST_EXTRAS),docs $(BIN)/python -m pytest -q -m "slow or not slow"

bench: $(STAMP)
	$(BIN)/python benchmarks/dynamics.py
	$(BIN)/python benchmarks/mesh_dimension.py
	$(BIN)/python benchmarks/mfpt.py
	$(BIN)/python benchmarks/apg.py --compile --learner-epochs 3
	$(BIN)/python benchmarks/finetune.py
	$(BIN)/python benchmarks/training.py
	$(BIN)/python benchmarks/mesh_scaling.py
	$(BIN)/python benchmarks/mujoco_rollout.py
	$(BIN)/python benchmarks/ray_scaling.py

# The documentation site, offline, into site/ (open site/index.html): the README as home page,
# ARCHITECTURE.md, the API reference from the docstrings and the four notebooks, executed
# during the build (about a minute on 2 cores; notebooks/ keeps no outputs).
docs: $(DOCS_STAMP)
	NO_MKDOCS_2_WARNING=1 $(BIN)/python -m mkdocs build

clean:
	rm -rf $(VENV) runs .pytest_cache site
