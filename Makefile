# The two README commands (`make demo`, `make test`) and the benchmark.
PYTHON ?= python3
VENV   := .venv
BIN    := $(VENV)/bin
STAMP  := $(VENV)/.installed-stamp

TEST_STAMP := $(VENV)/.test-stamp

.PHONY: demo test lint bench clean mutation

## `make demo`: only Python, as any user (no Debian packages, no native extras).
$(STAMP): pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(BIN)/pip install --quiet --upgrade pip
	$(BIN)/pip install --quiet -e .
	touch $(STAMP)

## `make test` and the other developer targets: the Debian packages the tests use (installing
## them needs root; as another user the script lists the missing ones), then the test extras
## (tpm2-pytss compiles against libtss2-dev).
$(TEST_STAMP): $(STAMP) pyproject.toml .ci/apt-packages
	bash .ci/install-system-deps
	$(BIN)/pip install --quiet -e '.[test]'
	touch $(TEST_STAMP)

## Resolve, lock, flatten and verify the bundled example robot, then resolve and verify
## the flattened document itself. It lives in examples/out and references the robot's
## files as ../robot/..., so every run that reads it names the folder holding both.
## Then build and verify its signed OTA release, publish and verify a registry holding a demo
## extension domain of our own (examples/robot/extensions) and the robot's stream profile,
## provision and export one device's MACsec keys, audit the robot and write its SBOM. Every
## key and passphrase is a throwaway one made in examples/out. Nothing here reads
## ../shared/corpus: a fresh clone with only Python runs it to the end.
## Each warning is said once: the verbs after the one that wrote a lock do not repeat what
## that lock now covers (docs/config.md, "Warnings").
demo: $(STAMP)
	rm -rf examples/out
	$(BIN)/hcdf-trust resolve examples/robot/robot.hcdf --locked --root examples --out examples/out/scout2.flat.hcdf
	$(BIN)/hcdf-trust verify examples/robot/robot.hcdf
	$(BIN)/hcdf-trust validate examples/out/scout2.flat.hcdf
	$(BIN)/hcdf-trust resolve examples/out/scout2.flat.hcdf --root examples
	$(BIN)/hcdf-trust verify examples/out/scout2.flat.hcdf --root examples
	$(BIN)/hcdf-trust ota keygen --type ecdsa-p256 -o examples/out/ota-demo-key.pem
	$(BIN)/hcdf-trust ota build examples/robot/robot.hcdf --firmware-dir examples/robot/firmware --key examples/out/ota-demo-key.pem --out examples/out/release --base-url https://firmware.example.com/scout2 --provenance
	$(BIN)/hcdf-trust ota verify examples/out/release --key examples/out/ota-demo-key.pub.pem --provenance
	umask 077 && head -c 24 /dev/urandom | base64 > examples/out/registry.pass && head -c 24 /dev/urandom | base64 > examples/out/macsec.pass
	$(BIN)/hcdf-trust registry init examples/out/registry --keys examples/out/registry-keys --passphrase-file examples/out/registry.pass
	$(BIN)/hcdf-trust registry keygen --keys examples/out/scout2-keys -o examples/out/scout2.pub --passphrase-file examples/out/registry.pass
	$(BIN)/hcdf-trust registry add examples/out/registry --domain com.example.scout2 --owner "Scout 2 (demo)" --owner-key examples/out/scout2.pub --version 1.0 --schema examples/robot/extensions/hcdf-ext-scout2.xsd --content examples/robot --keys examples/out/scout2-keys --passphrase-file examples/out/registry.pass
	$(BIN)/hcdf-trust registry add examples/out/registry --profile examples/robot/profiles/operational.streams.xml --content examples/robot
	$(BIN)/hcdf-trust registry publish examples/out/registry --keys examples/out/registry-keys --keys examples/out/scout2-keys --content examples/robot --out examples/out/registry-site --passphrase-file examples/out/registry.pass
	$(BIN)/hcdf-trust registry verify examples/out/registry-site --trusted-root examples/out/registry-site/metadata/1.root.json --cache-dir examples/out/registry-client
	$(BIN)/hcdf-trust macsec plan examples/robot/robot.hcdf
	$(BIN)/hcdf-trust macsec generate examples/robot/robot.hcdf --store examples/out/macsec --passphrase-file examples/out/macsec.pass
	$(BIN)/hcdf-trust macsec export examples/robot/robot.hcdf --store examples/out/macsec --passphrase-file examples/out/macsec.pass --device compute --format iproute2 --out examples/out/macsec-compute
	$(BIN)/hcdf-trust audit examples/robot/robot.hcdf --policy examples/audit-policy.toml --release examples/out/release --key examples/out/ota-demo-key.pub.pem --store examples/out/macsec --passphrase-file examples/out/macsec.pass
	$(BIN)/hcdf-trust sbom examples/robot/robot.hcdf --format cyclonedx --release examples/out/release --key examples/out/ota-demo-key.pub.pem -o examples/out/scout2.cdx.json
	@echo
	@echo "Done. The command is installed in $(abspath $(BIN)): run $(abspath $(BIN))/hcdf-trust --help,"
	@echo "or put it on PATH: export PATH=\"$(abspath $(BIN)):\$$PATH\" (see Install in README.md)."

## The whole test suite (what CI runs); installs the Debian packages the tests need first.
test: $(TEST_STAMP)
	bash .ci/install-system-deps
	$(BIN)/ruff check hcdf_trust tests bench
	$(BIN)/mypy hcdf_trust
	$(BIN)/pytest -n 2 -q

lint: $(TEST_STAMP)
	$(BIN)/ruff check hcdf_trust tests bench
	$(BIN)/mypy hcdf_trust

clean:
	rm -rf $(VENV) examples/out bench/work .pytest_cache mutants

## Ratio benchmarks (a few minutes, not part of `make test`); writes bench/RESULTS.md.
bench: $(TEST_STAMP)
	$(BIN)/python bench/run.py $(BENCH_ARGS)
	$(BIN)/python bench/jsonform.py

## Mutation testing of the verification core (slow; not part of `make test`). One worker: the
## machine is shared. Resumes where it stopped; MUTANTS='hcdf_trust.digest.*' narrows it.
## The corpus is passed explicitly: mutmut runs the tests from a copy in mutants/.
MUTANTS ?=
mutation: $(TEST_STAMP)
	$(BIN)/pip install --quiet -e '.[test,mutation]'
	HCDF_CORPUS="$${HCDF_CORPUS:-$(abspath $(CURDIR)/..)/shared/corpus}" HCDF_FUZZ_EXAMPLES="$${HCDF_FUZZ_EXAMPLES:-10}" \
		$(BIN)/mutmut run --max-children 1 $(MUTANTS)
	$(BIN)/python tests/mutation_summary.py
