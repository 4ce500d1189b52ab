"""One module per `vitfly` subcommand: add_arguments(parser) and run(args) -> int (``engine_flags``: the
simulator-engine flags that several of them take)."""
