# Two commands do all the set-up on a fresh machine: `make demo` and `make test`.
PYTHON ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed-stamp

.PHONY: install demo test bench ablation study coverage realdata samples lint clean

$(STAMP): pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet -e ".[test]"
	$(BIN)/python -m batgraph.warm  # compile the numba kernels now, not in the first reconstruct
	touch $(STAMP)

install: $(STAMP)

## demo: reconstruct the bundled flight and ear samples with every method (outputs in out/)
demo: install
	$(BIN)/batgraph reconstruct data/samples/flight_5cam --out out/flight_5cam --compare
	$(BIN)/batgraph reconstruct data/samples/ear_2cam --out out/ear_2cam --compare

## test: the test suite (what CI runs), one worker per core (pytest-xdist; about 7 minutes on 2 cores)
test: install
	$(BIN)/python -m pytest -q -ra -n auto

## bench: speed, ratios against baselines measured in the same run (BENCHMARKS.md; about 19 minutes on 2 cores)
bench: install
	$(BIN)/python scripts/bench.py
	$(BIN)/python scripts/bench_growth.py
	$(BIN)/python scripts/bench_associate.py --repeats 3
	$(BIN)/python scripts/bench_detect.py --repeats 3
	test -x .venv-bench/bin/python || ($(PYTHON) -m venv .venv-bench && .venv-bench/bin/python -m pip install --quiet aniposelib)
	$(BIN)/python scripts/bench_aniposelib.py export bench_out/aniposelib
	.venv-bench/bin/python scripts/bench_aniposelib.py run bench_out/aniposelib

## ablation: the smoother's post-solve steps and floors switched off one at a time (writes docs/ablation.md)
ablation: install
	$(BIN)/python scripts/ablation.py

## study: the ablation, then the accuracy study (writes docs/accuracy.md, with the ablation's summary)
study: ablation
	$(BIN)/python scripts/accuracy_study.py

## coverage: the default smoother's 95 % coverage by status and span pooled over seeds 1-10 (docs/coverage_seeds.md)
coverage: install
	$(BIN)/python scripts/coverage_seeds.py

## realdata: every real dataset in ../shared/data/real through reconstruct --validate (docs/real_data.md)
realdata: install
	$(BIN)/python scripts/real_data_study.py

## samples: regenerate the bundled samples (deterministic)
samples: install
	$(BIN)/batgraph simulate flight data/samples/flight_5cam --cameras 5 --markers 24 --frames 160 --seed 1 --force
	$(BIN)/batgraph simulate ear data/samples/ear_2cam --frames 250 --seed 1 --force

lint: install
	$(BIN)/ruff check batgraph scripts tests

clean:
	rm -rf out bench_out .pytest_cache
