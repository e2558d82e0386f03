# glasscan — the two commands of the README, and helpers.
#   make demo   build and run the zero-setup demo on a built-in object
#   make test   build and run the whole test suite
# Both first make sure the Debian packages the build needs are installed.

DEBIAN_PACKAGES := libembree-dev libopencv-dev libopencv-contrib-dev libhdf5-dev clang libclang-dev cmake pkg-config fonts-dejavu-core
CARGO ?= cargo

.PHONY: deps demo test test-embree4 lint lib-check fuzz bench bench-remesh bench-simulate clean

# Installs missing Debian packages when run as root (waiting up to 10 minutes for another apt or
# dpkg to finish, and stopping if apt-get fails); otherwise prints the exact command and stops.
deps:
	@missing=""; \
	for p in $(DEBIAN_PACKAGES); do \
	  dpkg-query -W -f='$${Status}' $$p 2>/dev/null | grep -q "install ok installed" || missing="$$missing $$p"; \
	done; \
	if [ -n "$$missing" ]; then \
	  if [ "$$(id -u)" = "0" ]; then \
	    echo "glasscan: installing$$missing"; \
	    n=0; until out=$$(apt-get update -qq 2>&1); do \
	      case "$$out" in *"Could not get lock"*) ;; *) echo "$$out"; n=60 ;; esac; \
	      n=$$((n + 1)); \
	      [ $$n -le 60 ] || { echo "glasscan: apt-get update failed (above): fix it and run make again"; exit 1; }; \
	      [ $$n -gt 1 ] || echo "glasscan: another apt-get holds the package lists; waiting up to 10 minutes"; \
	      sleep 10; \
	    done; \
	    DEBIAN_FRONTEND=noninteractive apt-get -o DPkg::Lock::Timeout=600 install -y -qq$$missing || \
	      { echo "glasscan: apt-get could not install$$missing (above): fix it and run make again"; exit 1; }; \
	  else \
	    echo "glasscan needs these Debian packages:$$missing"; \
	    echo "install them with:  sudo apt-get install -y$$missing"; \
	    exit 1; \
	  fi; \
	fi; \
	command -v $(CARGO) >/dev/null || { echo "glasscan needs Rust >= 1.89 (cargo): install it with rustup, https://rustup.rs"; exit 1; }

demo: deps
	$(CARGO) run --release -- demo --out demo-out

# The tests also compare against OpenCV's own sample calibration (package opencv-doc) and show
# the capture's pattern window in a virtual X server (package xvfb).
test: DEBIAN_PACKAGES += opencv-doc xvfb
test: deps
	$(CARGO) test --release

# The whole test suite again against Embree 4.4.0 (Debian 12 ships only Embree 3): headers from
# the folder EMBREE4 (with include/embree4/ and get-lib.sh, which fetches the matching library
# from PyPI with pip into target/embree4-lib). Leaves the build linked against Embree 4; the next
# `make test` relinks against the system's Embree.
EMBREE4 ?= ../shared/embree4
EMBREE4_LIB := $(CURDIR)/target/embree4-lib
test-embree4: DEBIAN_PACKAGES += opencv-doc xvfb
test-embree4: deps
	@[ -f "$(EMBREE4)/get-lib.sh" ] && [ -f "$(EMBREE4)/include/embree4/rtcore.h" ] || \
	  { echo "glasscan: $(EMBREE4) has no Embree 4 headers and get-lib.sh: set EMBREE4=folder"; exit 1; }
	bash "$(EMBREE4)/get-lib.sh" "$(EMBREE4_LIB)"
	EMBREE4_INCLUDE_DIR="$(abspath $(EMBREE4))/include" EMBREE4_LIB_DIR="$(EMBREE4_LIB)" \
	  $(CARGO) run --release -- --version | grep -F "Embree 4."
	EMBREE4_INCLUDE_DIR="$(abspath $(EMBREE4))/include" EMBREE4_LIB_DIR="$(EMBREE4_LIB)" \
	  $(CARGO) test --release

# The readers' fuzz tests at 100,000 cases each (`make test` runs 64).
fuzz: deps
	GLASSCAN_FUZZ_CASES=100000 $(CARGO) test --release --test fuzz_readers -- --nocapture

# Formatting and lint checks (CI runs them beside the tests).
lint:
	$(CARGO) fmt --check
	$(CARGO) clippy --release --all-targets -- -D warnings

# The library alone builds without the command line, HDF5 and live capture, and then depends on
# none of clap, indicatif, ctrlc, hdf5 or OpenCV's highgui and videoio.
lib-check: deps
	$(CARGO) build --release --lib --no-default-features
	@if $(CARGO) tree --no-default-features -e normal | grep -E ' (clap|indicatif|ctrlc|hdf5-metno|ndarray) '; then \
	  echo "glasscan: the library without default features depends on the crates above"; exit 1; fi
	@if $(CARGO) tree --no-default-features -e features -i opencv | grep -E 'highgui|videoio'; then \
	  echo "glasscan: the library without default features builds OpenCV's highgui or videoio"; exit 1; fi
	@echo "glasscan: the library builds alone"

# Embree throughput on a mesh: make bench MESH=../shared/meshes/pig_scan.ply
MESH ?= ../shared/meshes/pig_scan.ply
bench: deps
	$(CARGO) run --release -- bench trace --mesh $(MESH)

# glasscan's remesher against pymeshlab's (installed by pip into a venv under target/).
PYMESHLAB_VENV := target/pymeshlab-venv
bench-remesh: deps
	@[ -x $(PYMESHLAB_VENV)/bin/python ] && $(PYMESHLAB_VENV)/bin/python -c "import pymeshlab" 2>/dev/null || \
	  { python3 -m venv $(PYMESHLAB_VENV) && $(PYMESHLAB_VENV)/bin/pip install -q pymeshlab; }
	$(CARGO) run --release -- bench remesh --meshes $(dir $(MESH)) --python $(PYMESHLAB_VENV)/bin/python --json target/bench-remesh.json

# A full 72-view scan of the horse at 1280×960 (the simulator prints its own time and figures).
bench-simulate: deps
	$(CARGO) run --release -- simulate --mesh $(dir $(MESH))horse_scan.ply --out target/horse-scan --views 72 --size 1280x960

clean:
	$(CARGO) clean
	rm -rf demo-out
