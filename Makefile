# cellrt — the two commands a user needs are `make run` and `make test`.
SHELL := bash
REBAR ?= rebar3
# The apps Debian ships inside rabbitmq-server (cowboy, ranch, jsx ...) and the cured
# PropEr live in _debdeps/; ERL_LIBS puts them on the code path, ahead of the system's.
export ERL_LIBS := $(CURDIR)/_debdeps
export CELLRT_TOP := $(CURDIR)

.PHONY: all setup setup-test compile release run vplc test bench soak chaos dist clean

all: compile

setup:
	@scripts/setup run

setup-test:
	@scripts/setup test

compile: setup
	@$(REBAR) compile

release: setup
	@$(REBAR) release

## Builds the release and starts the default cell in the foreground, in real mode over
## Modbus TCP against a virtual PLC of its own (scripts/vplc, stopped with the cell);
## CELLRT_SIM=vm for the in-VM simulated PLC instead. Ctrl-C stops it.
run: release
	@scripts/run

## A virtual PLC: the default cell's simulated machine over Modbus TCP (port 1502), for
## the cell in real mode, an HMI or a SCADA; VPLC_ARGS for scripts/vplc's options.
vplc: compile
	@scripts/vplc $(VPLC_ARGS)

## eunit (with PropEr properties), common_test suites, xref, dialyzer, system tests.
test: setup-test
	@scripts/test

## Every benchmark, each beside its peer; rewrites docs/benchmarks.md.
bench: setup-test
	@scripts/bench

## The default cell for SOAK_MINUTES (default 30) at a high rate: memory and message
## queues over time; not part of `make test`. A run of 30 minutes rewrites docs/soak.md.
soak: setup
	@scripts/bench soak

## The chaos test: the release killed CHAOS_NODE_KILLS times (default 200) and
## CHAOS_PROC_KILLS processes in it (default 1000), CHAOS_SEED; every serial reconciled
## with the simulated machine. Not part of `make test` (its bounded form is). A run at
## full size rewrites docs/chaos.md.
chaos: setup
	@scripts/chaos

## A self-contained tarball of the release with ERTS.
dist: setup
	@$(REBAR) as prod tar
	@ls -1 _build/prod/rel/cellrt/cellrt-*.tar.gz

clean:
	@$(REBAR) clean -a
	rm -rf _build
