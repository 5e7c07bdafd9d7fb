# softgrasp: everything installs into a project-local virtual environment (.venv).
PY ?= python3
VENV := .venv
BIN := $(VENV)/bin

.PHONY: run test install install-test browser gl bench clean

$(BIN)/python:
	$(PY) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip

# softgrasp with both optional extras: MuJoCo (`execute`) and Dask with PyArrow (`sweep`); then
# its bytecode is written (an editable install writes none, and where PYTHONDONTWRITEBYTECODE is
# set, as in many containers, every run would compile every module: ~0.12 s of a plan) and its
# kernels compile once (about a minute on a first install, the solvers a plan does not use
# included; nothing to do after).
install: $(BIN)/python gl
	$(BIN)/python -m pip install --quiet -e ".[execute,sweep]"
	$(BIN)/python -m compileall -q src/softgrasp
	$(BIN)/python -m softgrasp.cli.warm

install-test: $(BIN)/python browser gl
	$(BIN)/python -m pip install --quiet -e ".[test,execute,sweep]"
	$(BIN)/python -m compileall -q src/softgrasp
	$(BIN)/python -m softgrasp.cli.warm

# Debian's Chromium and ChromeDriver for the browser test of `softgrasp view` (installed when
# missing and apt-get can run; otherwise that test is skipped and says why).
browser:
	@if [ ! -x /usr/bin/chromium ] || [ ! -x /usr/bin/chromedriver ]; then \
	  if command -v apt-get >/dev/null 2>&1 && [ "$$(id -u)" = 0 ]; then \
	    (apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq chromium chromium-driver >/dev/null) \
	      || echo "softgrasp: could not install chromium; the browser test will be skipped"; \
	  else echo "softgrasp: no chromium and no root apt-get; the browser test will be skipped"; fi; \
	fi

# Debian's Mesa EGL, with which MuJoCo renders `softgrasp execute`'s pictures without a screen
# (MUJOCO_GL=egl; installed when missing and apt-get can run; otherwise matplotlib draws them).
GL_PACKAGES := libegl1 libegl-mesa0 libgl1-mesa-dri
gl:
	@if [ "$$(dpkg-query -W -f='$${Status}\n' $(GL_PACKAGES) 2>/dev/null | grep -c 'install ok installed')" \
	  = "$(words $(GL_PACKAGES))" ]; then :; \
	elif command -v apt-get >/dev/null 2>&1 && [ "$$(id -u)" = 0 ]; then \
	  (apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq $(GL_PACKAGES) >/dev/null) \
	    || echo "softgrasp: could not install $(GL_PACKAGES); execute's pictures will be drawn by matplotlib"; \
	else echo "softgrasp: no $(GL_PACKAGES) and no root apt-get; execute's pictures will be drawn by matplotlib"; fi

# The main job on the built-in default object.
run: install
	$(BIN)/softgrasp plan

# The whole test suite (slow tests included), on one pytest-xdist worker per core.
test: install-test
	$(BIN)/python -m pytest -n auto --dist worksteal

bench: install
	$(BIN)/python benchmarks/bench_body.py
	$(BIN)/python benchmarks/bench_contact.py
	$(BIN)/python benchmarks/bench_plan.py --reference
	$(BIN)/python benchmarks/bench_reach.py
	$(BIN)/python benchmarks/bench_settle.py
	$(BIN)/python benchmarks/bench_dynamic.py
	$(BIN)/python benchmarks/bench_indent.py
	$(BIN)/python benchmarks/bench_execute.py
	$(BIN)/python benchmarks/bench_sweep.py
	$(BIN)/python benchmarks/bench_revisions.py

clean:
	rm -rf $(VENV) softgrasp-out .pytest_cache
