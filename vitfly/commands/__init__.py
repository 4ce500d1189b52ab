"""One module per `vitfly` subcommand: add_arguments(parser) and run(args) -> int."""
