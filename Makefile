# rvnoise — two commands on a fresh machine: `make demo` and `make test`.
PY      ?= python3
VENV    := .venv
BIN     := $(VENV)/bin
STAMP   := $(VENV)/.installed
DEMO    := out/demo

.PHONY: demo test bench sample-data install check-open3d clean

install: $(STAMP)

$(STAMP): pyproject.toml
	$(PY) -m venv $(VENV)
	$(BIN)/pip install --quiet --upgrade pip
	$(BIN)/pip install --quiet -e '.[dev,onnx,dask,arrow,heif]'
	@$(MAKE) --no-print-directory check-open3d
	@touch $(STAMP)

# open3d's wheel needs libusb-1.0.so.0 to import: install it with apt-get when we can, else say what to install.
check-open3d:
	@if ! $(BIN)/python -c "import open3d" >/dev/null 2>&1; then \
	  if ldconfig -p 2>/dev/null | grep -q 'libusb-1.0.so.0'; then $(BIN)/python -c "import open3d"; exit 1; fi; \
	  if command -v apt-get >/dev/null 2>&1 && [ "$$(id -u)" = 0 ]; then \
	    echo "installing libusb-1.0-0 (needed by open3d)"; \
	    apt-get install -y -qq libusb-1.0-0 >/dev/null 2>&1 || { apt-get update -qq && apt-get install -y -qq libusb-1.0-0; }; \
	  else \
	    echo "open3d needs libusb-1.0.so.0: run 'sudo apt-get install libusb-1.0-0' (Debian/Ubuntu) and retry"; exit 1; \
	  fi; \
	  $(BIN)/python -c "import open3d"; \
	fi

demo: $(STAMP)
	@rm -rf $(DEMO)
	$(BIN)/rvnoise augment --recipe recipes/cnf16.yaml sample_data $(DEMO)/cnf16-camera-wind-rain --quiet
	$(BIN)/rvnoise augment --recipe recipes/cnf20.yaml sample_data $(DEMO)/cnf20-lidar-alignment-fog --quiet
	$(BIN)/rvnoise augment --recipe recipes/cnf25-radar.yaml sample_data $(DEMO)/cnf25-radar-rain-obstruction --quiet
	$(BIN)/rvnoise report $(DEMO)
	@echo "demo done: open $(DEMO)/report.html (one folder per recipe in $(DEMO)/: augmented files, manifest.jsonl, run.json)"

test: $(STAMP)
	$(BIN)/python -m pytest -p no:cacheprovider

# bench/run.py: the one table of README "Performance"; the per-model scripts after it
bench: $(STAMP)
	$(BIN)/python bench/run.py
	@for b in bench/bench_*.py; do echo "== $$b"; $(BIN)/python $$b || exit 1; done

sample-data: $(STAMP)
	rm -rf sample_data
	$(BIN)/python -m roadview_noise.sampledata.generate sample_data --frames 3 --seed 0 --camera-size 484x366 --lidar-columns 256

clean:
	rm -rf out build *.egg-info .pytest_cache
