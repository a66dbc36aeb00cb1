# Causeway: the one entry point. `make run` and `make test` work on a fresh machine.
SHELL := /bin/bash
PYTHON ?= python3
VENV ?= .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed
ARGS ?=
N ?= 2
# Compose v2 (`docker compose`) where the docker CLI has it, else docker-compose 1.29 (Debian's).
COMPOSE ?= $(shell docker compose version >/dev/null 2>&1 && echo "docker compose" || echo docker-compose)

.PHONY: run test test-compose sysdeps-compose bus-secrets test-slow test-all bench bench-f1 bench-collection bench-ch3 lint up down scale logs sysdeps clean venv

venv: $(STAMP)

# torch first, exactly pinned, so pip takes the local CPU wheel instead of a CUDA build.
$(STAMP): pyproject.toml
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install -q --disable-pip-version-check torch==2.13.0
	$(PY) -m pip install -q --disable-pip-version-check -e '.[test,deploy,dmc]'
	touch $@

# Debian tools the integration tests drive for real (validators, Prometheus, Chromium).
sysdeps:
	@missing=""; \
	command -v docker-compose >/dev/null || missing="$$missing docker-compose"; \
	command -v prometheus >/dev/null || missing="$$missing prometheus"; \
	command -v promtool >/dev/null || missing="$$missing prometheus"; \
	command -v chromium >/dev/null || missing="$$missing chromium"; \
	if [ -n "$$missing" ]; then \
	  if [ "$$(id -u)" = 0 ] && command -v apt-get >/dev/null; then \
	    apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq --no-install-recommends $$missing >/dev/null; \
	  else echo "warning: missing$$missing (tests that need them will be skipped)"; fi; \
	fi

# The main job: CDL on Chemical (10 objects, full graph) until the paper's F1 (0.95 at the best
# threshold, as Table 3.1 reports it) or 15 minutes; ARGS overrides any flag.
run: $(STAMP)
	$(PY) -m services.cli run --target-f1 0.95 --target-metric best_threshold_f1 $(ARGS)

test: $(STAMP) sysdeps
	$(PY) -m pytest -q

# The compose stack built and run for real on a private dockerd (tests/deploy/test_compose_stack.py):
# stand-in base images (cached in ~/.cache/causeway/compose-test), the image from deploy/Dockerfile,
# compose.yaml + tests/deploy/compose.smoke.yaml. Skips, saying why, where no engine can start.
test-compose: $(STAMP) sysdeps sysdeps-compose
	@status=0; $(PY) -m pytest -q -p no:cacheprovider -m slow --timeout=3600 tests/deploy/test_compose_stack.py || status=$$?; \
	  test -f test-artifacts/compose/figures.json && cat test-artifacts/compose/figures.json; exit $$status

# Docker engine, docker-compose 1.29 and debootstrap from Debian, for test-compose. The packages'
# scripts must not start a system dockerd (policy-rc.d), and another apt may hold the dpkg lock.
sysdeps-compose:
	@missing=""; \
	command -v dockerd >/dev/null || missing="$$missing docker.io"; \
	command -v docker-compose >/dev/null || missing="$$missing docker-compose"; \
	command -v debootstrap >/dev/null || missing="$$missing debootstrap"; \
	if [ -n "$$missing" ]; then \
	  if [ "$$(id -u)" = 0 ] && command -v apt-get >/dev/null; then \
	    made=""; if [ ! -e /usr/sbin/policy-rc.d ]; then printf '#!/bin/sh\nexit 101\n' > /usr/sbin/policy-rc.d; \
	      chmod +x /usr/sbin/policy-rc.d; made=1; fi; \
	    apt-get -o DPkg::Lock::Timeout=600 update -qq; \
	    DEBIAN_FRONTEND=noninteractive apt-get -o DPkg::Lock::Timeout=600 install -y -qq --no-install-recommends \
	      $$missing >/dev/null; status=$$?; \
	    if [ -n "$$made" ]; then rm -f /usr/sbin/policy-rc.d; fi; exit $$status; \
	  else echo "warning: missing$$missing (test-compose will be skipped)"; fi; \
	fi

test-slow: $(STAMP) sysdeps
	$(PY) -m pytest -q -m slow

test-all: $(STAMP) sysdeps
	$(PY) -m pytest -q -m ''

bench: $(STAMP)
	$(PY) -m benchmarks.run_all $(ARGS)

bench-f1: $(STAMP)
	$(PY) -m benchmarks.bench_time_to_f1 $(ARGS)

bench-collection: $(STAMP)
	$(PY) -m benchmarks.bench_collection $(ARGS)

bench-ch3: $(STAMP)
	$(PY) -m benchmarks.bench_ch3_generalisation --graphs chain full collider --num-objects 10 \
		--transitions 100000 --updates 3000 --prediction-starts 2000 --match-graphs full --match-episodes 16 $(ARGS)

lint: $(STAMP)
	$(PY) -m pyflakes services proto envs causal benchmarks tests

# Compose secrets are bind mounts that keep the file's host owner and mode (outside Swarm compose
# ignores uid/gid/mode), and the containers run as other users (causeway: 10001, grafana: 472), so
# the files are 644 and the git-ignored directory deploy/secrets/ 700: private on the host, readable
# in the containers they are mounted into.
# Grafana's admin password: generated once per checkout, read by compose as a secret;
# GRAFANA_ADMIN_PASSWORD_FILE=path uses another file instead.
GRAFANA_SECRET := deploy/secrets/grafana-admin-password

$(GRAFANA_SECRET):
	@mkdir -p $(dir $@) && chmod 700 $(dir $@) && umask 022 && \
	  $(PYTHON) -c "import secrets; print(secrets.token_urlsafe(24))" > $@
	@echo "Grafana admin password generated in $@ (user admin)"

# Roles on the bus (docs/bus-roles.md): every role's credentials, the router's users file and its
# configuration with authentication and access control, generated once per checkout. The keys name
# the run id and the method: after changing CAUSEWAY_RUN_ID or CAUSEWAY_METHOD, `rm -r deploy/secrets`
# and `make up` again (new passwords need the whole stack restarted). CAUSEWAY_EXTRACTOR=frames|latent
# adds the factor-extractor's role for deploy/compose.frames.yaml or deploy/compose.labels.yaml.
BUS_SECRETS := deploy/secrets/router.json5

$(BUS_SECRETS): | $(STAMP)
	@$(PY) -m services.cli bus-secrets --run $${CAUSEWAY_RUN_ID:-compose} --method $${CAUSEWAY_METHOD:-cdl} \
	  --extractor $${CAUSEWAY_EXTRACTOR:-none} --out $(patsubst %/secrets/,%,$(dir $@)) --file-mode 644

bus-secrets: $(BUS_SECRETS)

up: $(GRAFANA_SECRET) $(BUS_SECRETS)
	$(COMPOSE) up -d --build

down:
	$(COMPOSE) down

scale: $(GRAFANA_SECRET) $(BUS_SECRETS)
	$(COMPOSE) up -d --scale env-worker=$(N) --no-recreate

logs:
	$(COMPOSE) logs -f --tail=100

clean:
	rm -rf $(VENV) runs .pytest_cache test-artifacts
