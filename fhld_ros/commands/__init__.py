"""`fhld` subcommands that drive the whole pipeline or run other subcommands: replay, demo,
bench, import, autolabel and autolabel-eval (simulate, autolabel and eval on held-out drives).
Commands that belong to one part live beside it (sim/simulate.py, training/train.py,
evaluation/, ros/play.py); cli.py lists them all."""
