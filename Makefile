# Two commands do all the set-up on a fresh machine:
#   make demo   install into .venv, then run the main job on its defaults
#   make test   install into .venv (with test tools), then lint and run the test suite
PYTHON ?= python3
VENV ?= .venv
BIN := $(VENV)/bin
# torch is pinned so that pip takes the CPU build that machines without a GPU keep in
# their local wheel folder, instead of resolving the newest release with its CUDA packages.
TORCH ?= torch==2.13.0
STAMP := $(VENV)/.installed

.PHONY: install demo test test-slow bench lint format clean

$(STAMP): pyproject.toml Makefile
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade "pip>=23"
	$(BIN)/python -m pip install --quiet "$(TORCH)" -e ".[dev]"
	@touch $(STAMP)

install: $(STAMP)

# The main job: train SAC with language hindsight relabelling on the fast 2D tabletop
# (reach instructions, a few minutes on a CPU), then evaluate the checkpoint on seen
# instructions, held-out word combinations and unseen phrasings.
demo: $(STAMP)
	$(BIN)/lcrl train lang2d-quick --out runs/main --overwrite
	$(BIN)/lcrl eval runs/main --episodes 100 --out runs/main/evals/final
	$(BIN)/lcrl report runs/main
	@echo "outputs: runs/main/report.md, runs/main/curves.png, runs/main/evals/final/, runs/main/checkpoints/"

test: $(STAMP)
	$(BIN)/ruff check .
	$(BIN)/ruff format --check .
	$(BIN)/pytest -q -n 2 --dist loadfile -m "not slow and not benchmark"

test-slow: $(STAMP)
	$(BIN)/pytest -q -m "slow" || [ $$? -eq 5 ]  # 5: no test carries the marker

bench: $(STAMP)
	$(BIN)/python -m pip install --quiet -e ".[bench]"
	$(BIN)/python -m benchmarks.env_speed
	$(BIN)/python -m benchmarks.text_encoder_speed
	$(BIN)/python -m benchmarks.speed_vs_sb3 --rounds 5
	$(BIN)/python -m benchmarks.learning_curves fetch-reach
	$(BIN)/python -m benchmarks.learning_curves lang2d --parallel
	$(BIN)/python -m benchmarks.captioning

lint: $(STAMP)
	$(BIN)/ruff check .
	$(BIN)/ruff format --check .

format: $(STAMP)
	$(BIN)/ruff format .
	$(BIN)/ruff check --fix .

clean:
	rm -rf $(VENV) runs .pytest_cache .ruff_cache
