"""`fhld` subcommands that drive the whole pipeline: replay, demo and bench. Commands that
belong to one part live beside it (sim/simulate.py, training/train.py, evaluation/, ros/play.py);
cli.py lists them all."""
