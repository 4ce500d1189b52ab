"""``vitfly configs [NAME]``: the configs shipped with vitfly (name, command, what it is, where it lives)."""

from __future__ import annotations

import argparse

from vitfly.errors import VitflyError
from vitfly.packaged import shipped_config, shipped_configs, shipped_dir

ABOUT_WIDTH = 72


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("name", nargs="?",
                        help="print only this config's path (to copy and edit it), e.g. quickstart or fit/vit_lstm")


def _short(text: str, width: int) -> str:
    return text if len(text) <= width else text[: width - 3].rstrip() + "..."


def run(args: argparse.Namespace) -> int:
    if args.name is not None:
        path = shipped_config(args.name)
        if path is None:
            raise VitflyError(f"{args.name}: no config of that name is shipped with vitfly (`vitfly configs` lists "
                              "them)")
        print(path)
        return 0
    configs = shipped_configs()
    if not configs:
        raise VitflyError("no shipped configs found: this vitfly was installed without its configs/ "
                          "(reinstall it from a wheel or a clone)")
    print(f"configs shipped with vitfly, in {shipped_dir('configs')} (NAME.yaml); "
          "use one by name, e.g. --config quickstart, or by path")
    name_w = max(len(c.name) for c in configs)
    cmd_w = max(len(c.command) for c in configs)
    print(f"{'name':<{name_w}}  {'for':<{cmd_w}}  what")
    for c in configs:
        print(f"{c.name:<{name_w}}  {c.command:<{cmd_w}}  {_short(c.about, ABOUT_WIDTH)}")
    return 0
