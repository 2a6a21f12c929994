"""The `detcal` command line (`main`); each subcommand is registered by the module that owns
it (`offline`: fit, evaluate, calibrate; `convert`; `export`; `serve`)."""
