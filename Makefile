# gainfpn: `make demo` and `make test` work from a fresh clone with only Python.
PYTHON ?= python3
VENV   := .venv
BIN    := $(VENV)/bin
STAMP  := $(VENV)/.installed-stamp

.PHONY: install test test-slow demo bench bench-quick sample-data clean

$(STAMP): pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet -e '.[test]'
	touch $(STAMP)

install: $(STAMP)  ## create .venv and install gainfpn with its test tools

test: $(STAMP)  ## the unit suite (slow end-to-end cases excluded), on 2 processes
	$(BIN)/python -m pytest -q -n 2

test-slow: $(STAMP)  ## only the slow end-to-end cases
	$(BIN)/python -m pytest -q -n 2 -m slow

demo: $(STAMP)  ## estimate a gain map from sample_data/exr_burst and score it against its truth
	$(BIN)/gainfpn estimate sample_data/exr_burst -o demo_out --overwrite
	@echo
	$(BIN)/gainfpn evaluate demo_out --truth sample_data/exr_burst
	@echo
	@echo "Outputs in demo_out/: gain_map.exr (k and confidence), corrected/, report.json, config.used.yaml, preview.png"

bench: $(STAMP)  ## the full speed/accuracy benchmark into bench_out/ (long: see README)
	$(BIN)/gainfpn bench -o bench_out --overwrite

bench-quick: $(STAMP)  ## the one-minute benchmark (CI smoke) into bench_quick/
	$(BIN)/gainfpn bench --quick -o bench_quick --overwrite

sample-data: $(STAMP)  ## regenerate sample_data/ (deterministic)
	$(BIN)/gainfpn simulate sample_data/exr_burst --overwrite --size 192x128 --frames 8 --seed 1
	$(BIN)/gainfpn simulate sample_data/dng_burst --overwrite --preset raw12 --size 160x128 --frames 8 --seed 2

clean:
	rm -rf $(VENV) build *.egg-info .pytest_cache .hypothesis
