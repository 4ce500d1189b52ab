"""The ``vitfly`` command.

``fit``, ``validate``, ``test`` and ``predict`` go to LightningCLI (``vitfly.training.cli``);
every other subcommand is one module under ``vitfly.commands`` with ``add_arguments(parser)``
and ``run(args) -> int``. Modules are imported lazily so ``vitfly --help`` stays quick.
"""

from __future__ import annotations

import argparse
import errno
import importlib
import os
import re
import sys

from vitfly.errors import VitflyError
from vitfly.host_memory import keep_freed_memory
from vitfly.packaged import version_line
from vitfly.quiet import quiet_third_party

LIGHTNING_SUBCOMMANDS = ("fit", "validate", "test", "predict")

# subcommand -> (module under vitfly.commands, one-line help)
SUBCOMMANDS: dict[str, tuple[str, str]] = {
    "collect": ("collect", "fly the privileged expert and write trajectories to HDF5"),
    "evaluate": ("evaluate", "fly a policy closed-loop and score it with the paper's metrics"),
    "ablate": ("ablate", "train with and without the state input and compare (paper's ablation)"),
    "benchmark-latency": ("benchmark_latency", "the paper's latency table for the model zoo"),
    "import-legacy": ("import_legacy", "import the original PNG + data.csv dataset into HDF5"),
    "convert-checkpoint": ("convert_checkpoint", "turn an original-project state dict into a vitfly checkpoint"),
    "export": ("export", "export a network for deployment (ONNX)"),
    "render": ("render", "draw a scene, a flown path and depth frames to PNG/GIF"),
    "explain": ("explain", "Grad-CAM and attention maps over one trial or N paired ones (PNG, GIF, numbers)"),
    "pipeline": ("pipeline", "the main job: collect if missing, train, fly against expert and straight, report"),
    "reproduce": ("reproduce", "the paper's results section: data, 11 trainings, every evaluation, results.md"),
    "dagger": ("dagger", "DAgger with the privileged expert beside behaviour cloning at equal labelled frames"),
    "publish-weights": ("publish_weights", "a trained checkpoint as weights/NAME.safetensors (fp16) + manifest"),
    "configs": ("configs", "the configs shipped with vitfly: names for --config, what each is, where it lives"),
    "weights": ("weights", "the pretrained weights at hand: names for pretrained:NAME, network, training, success"),
}


class _PrintVersion(argparse.Action):
    """``--version``: one line, never wrapped (argparse's own version action wraps long paths)."""

    def __init__(self, option_strings, dest, **kwargs):
        super().__init__(option_strings, dest, nargs=0, **kwargs)

    def __call__(self, parser, namespace, values, option_string=None):
        print(version_line())
        parser.exit()


def _build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="vitfly",
        description="ViTfly: end-to-end vision-based quadrotor obstacle avoidance. "
        f"Training subcommands ({', '.join(LIGHTNING_SUBCOMMANDS)}) are LightningCLI: "
        "see `vitfly fit --help`.",
    )
    parser.add_argument("--version", action=_PrintVersion, help="vitfly's version and where it runs from, then exit")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name in LIGHTNING_SUBCOMMANDS:
        sub.add_parser(name, help=f"LightningCLI {name} (vitfly {name} --config X.yaml)", add_help=False)
    for name, (_, help_text) in SUBCOMMANDS.items():
        sub.add_parser(name, help=help_text, add_help=False)
    return parser


def os_error_line(err: OSError) -> str:
    """One line for an error of the operating system: the path, what went wrong, what to do."""
    what = err.strerror or str(err)
    where = err.filename if err.filename is not None else ""
    h5 = re.search(r"name = '([^']+)'.*?error message = '([^']+)'", what)  # h5py names the file in its message
    if not where and h5:
        where, what = h5.group(1), h5.group(2)
    # writers create a hidden temporary beside the output (.NAME.tmp-PID): name the output itself
    where = re.sub(r"(^|/)\.([^/]+?)\.(tmp-\d+|[A-Za-z0-9_]{8}\.tmp\.\w+)$", r"\1\2", str(where))
    hint = {errno.ENOSPC: "; free some space and rerun the same command to resume",
            errno.EDQUOT: "; free some space and rerun the same command to resume",
            errno.EACCES: "; choose a location you may write to",
            errno.EROFS: "; choose a location you may write to",
            errno.ENOENT: "; check that the folder exists and is writable"}.get(err.errno, "")
    return " ".join(f"{where + ': ' if where else ''}{what}{hint}".split())


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    parser = _build_parser()
    if not argv or argv[0] not in (*LIGHTNING_SUBCOMMANDS, *SUBCOMMANDS):
        parser.parse_args(argv or ["--help"])  # prints help or the "invalid choice" error
        return 2
    command, rest = argv[0], argv[1:]
    quiet_third_party()  # Lightning's tips and known dependency warnings; vitfly's own output stays
    keep_freed_memory()  # CPU training and flying reuse freed memory instead of faulting pages in each step
    try:
        if command in LIGHTNING_SUBCOMMANDS:
            from vitfly.training.cli import run_lightning_cli

            return run_lightning_cli([command, *rest])
        module = importlib.import_module(f"vitfly.commands.{SUBCOMMANDS[command][0]}")
        sub_parser = argparse.ArgumentParser(
            prog=f"vitfly {command}",
            description=SUBCOMMANDS[command][1],
            formatter_class=argparse.ArgumentDefaultsHelpFormatter,
        )
        module.add_arguments(sub_parser)
        return int(module.run(sub_parser.parse_args(rest)) or 0)
    except VitflyError as err:
        print(f"vitfly: error: {err}", file=sys.stderr)
        return 2
    except BrokenPipeError:  # the reader stopped early (`vitfly weights | head`): end quietly, as Unix tools do
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())  # no second error when Python flushes
        return 141
    except OSError as err:  # an unwritable or missing location, permission denied, a full disk: bad input too
        print(f"vitfly: error: {os_error_line(err)}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("vitfly: interrupted; rerun the same command to resume", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
