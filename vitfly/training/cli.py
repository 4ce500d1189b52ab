"""``vitfly fit | validate | test | predict``: LightningCLI over PolicyModule and TrajectoryDataModule.

``--config`` takes a path or the name of a config shipped with vitfly (``--config fit/vit_lstm``: the
``configs/fit/vit_lstm.yaml`` of a clone or of the installed package; `vitfly configs` lists them).
YAML (omegaconf interpolation allowed)::

    seed_everything: 0
    model: vit_lstm                 # a registered network name, or a class path with init_args
    data: {data_path: data/spheres.h5}
    trainer: {max_epochs: 100}

Defaults: CSV logger (TensorBoard or wandb via ``trainer.logger``; wandb stays offline unless
WANDB_MODE says otherwise), a rich progress bar, checkpoints ``checkpoints/best.ckpt`` (lowest
``val/loss``) and ``checkpoints/last.ckpt`` in the run directory (``checkpoint.*`` flags), and the
train/validation split in ``split.json`` beside them. Resume with ``--ckpt_path .../last.ckpt``.
Fine-tune with ``fit --init_weights pretrained:vit_lstm`` (or a checkpoint of the same network): the network
starts from those weights, with a fresh optimiser and schedule; a resumed run ignores it.

With ``--ckpt_path`` (any subcommand) the checkpoint decides the network: its architecture,
``use_state`` and ``model_kwargs`` replace the config's (one line says so when they differ), so a
no-state checkpoint is validated, tested and predicted without state inputs. Everything else (lr,
tbptt_steps, ...) comes from the config and flags.
"""

from __future__ import annotations

import sys
import warnings
from pathlib import Path
from typing import Any

from lightning.pytorch.callbacks import ModelCheckpoint, ProgressBar, RichProgressBar
from lightning.pytorch.cli import LightningArgumentParser, LightningCLI

from vitfly.datamodules.datamodule import TrajectoryDataModule
from vitfly.packaged import find_config
from vitfly.training.checkpoints import LastCheckpoint
from vitfly.training.epoch_times import EpochTimes
from vitfly.training.fit import checkpoint_defaults, default_wandb_offline, finish_wandb
from vitfly.training.precision import usable_precision
from vitfly.zoo.checkpoint import network_hparams
from vitfly.zoo.legacy import read_torch_file
from vitfly.zoo.policy import PolicyModule, check_policy_arguments, policy_class, register_policy_classes

SUBCOMMANDS = ("fit", "validate", "test", "predict")
POLICY_CHECKED = ("avoid_weight", "tbptt_steps", "compile", "static_shapes", "cpu_threads", "channels_last")
RUN_ROOT = "runs"  # where runs go when trainer.default_root_dir is not set
# save_dir "" means "the run directory" (trainer.default_root_dir), filled in before instantiation so
# that a --trainer.default_root_dir override moves the logs too (YAML interpolation would not)
DEFAULT_LOGGER = {
    "class_path": "lightning.pytorch.loggers.CSVLogger",
    "init_args": {"save_dir": "", "name": ""},
}


class VitflyCLI(LightningCLI):
    """LightningCLI with vitfly's defaults: forced best/last checkpoints, CSV logger, rich progress bar.

    ``checkpoint.*`` configures the best checkpoint; last.ckpt (``LastCheckpoint``) is added beside it.
    """

    def add_arguments_to_parser(self, parser: LightningArgumentParser) -> None:
        parser.add_lightning_class_args(ModelCheckpoint, "checkpoint")
        parser.set_defaults({f"checkpoint.{k}": v for k, v in checkpoint_defaults().items()})
        parser.set_defaults({"trainer.logger": DEFAULT_LOGGER})
        # the datamodule's batch sampler shards itself across DDP ranks; Lightning cannot inject its own
        parser.set_defaults({"trainer.use_distributed_sampler": False})
        # the datamodule records use_state with the split; the policy's value is the one that counts
        parser.link_arguments("model.init_args.use_state", "data.use_state")
        parser.add_argument("--init_weights", type=str | None, default=None,
                            help="fit: start the network from pretrained:NAME or a checkpoint of the same network")

    def parse_arguments(self, parser: LightningArgumentParser, args: Any) -> None:
        super().parse_arguments(parser, args)
        if not hasattr(LightningCLI, "_parse_ckpt_path"):  # Lightning < 2.5 never calls it
            self._parse_ckpt_path()

    def _parse_ckpt_path(self) -> None:
        """Take the network (architecture, use_state, model_kwargs) from ``--ckpt_path``; replaces Lightning's
        version, which copies every stored hyper-parameter over the config."""
        subcommand = self.config.get("subcommand")
        ckpt_path = self.config[subcommand].get("ckpt_path") if subcommand else None
        if not ckpt_path or not Path(ckpt_path).is_file():
            return  # "last"/"best"/"hpc", or a missing file: Lightning resolves or reports those
        stored = network_hparams(read_torch_file(ckpt_path), str(ckpt_path))
        model = self.config[subcommand].model
        init = model.init_args
        current = {
            "model": init.get("model") or _default_model(model.class_path),
            "use_state": init.get("use_state"),
            "model_kwargs": dict(init.get("model_kwargs") or {}),
        }
        if current == stored:
            return
        update = {
            "class_path": f"{policy_class(stored['model']).__module__}.{stored['model']}",
            "init_args": {**stored, "model_kwargs": stored["model_kwargs"] or None},
        }
        self.config = self.parser.parse_object({subcommand: {"model": update}}, self.config)
        self.config[subcommand].data.use_state = stored["use_state"]  # the link target, recorded with the split
        print(
            f"vitfly {subcommand}: {ckpt_path} holds {stored['model']} (use_state={stored['use_state']}, "
            f"model_kwargs={stored['model_kwargs']}); using it instead of the config's {current['model']} "
            f"(use_state={current['use_state']}, model_kwargs={current['model_kwargs']})",
            file=sys.stderr,
        )

    def before_fit(self) -> None:
        """``--init_weights``: copy the weights into the fresh network (a resumed run already holds its own)."""
        config = self.config[self.subcommand]
        if config.get("init_weights") and not config.get("ckpt_path"):
            from vitfly.training.fit import load_initial_weights

            load_initial_weights(self.model, config.init_weights, self.model.hparams["model"],
                                 self.model.hparams["use_state"])

    def before_instantiate_classes(self) -> None:
        config = self.config[self.subcommand] if self.subcommand else self.config
        # bad PolicyModule arguments as one line (jsonargparse would wrap the error in a page of its own)
        init_args = getattr(config.model, "init_args", None) or {}
        check_policy_arguments(**{k: init_args[k] for k in POLICY_CHECKED if k in init_args})
        # bf16 autocast only where the CPU has bf16 kernels (the config saved beside the run says what ran)
        trainer = config.trainer
        trainer.precision, self.precision_notes = usable_precision(trainer.precision, trainer.accelerator,
                                                                   f"vitfly {self.subcommand}")
        root = config.trainer.default_root_dir or RUN_ROOT
        loggers = config.trainer.logger
        for logger in loggers if isinstance(loggers, list) else [loggers]:
            init_args = getattr(logger, "init_args", None)
            if init_args is not None and "save_dir" in init_args and not init_args.save_dir:
                init_args.save_dir = root

    def _instantiate_trainer(self, config: dict[str, Any], callbacks: list) -> Any:
        listed = config.get("callbacks") or []
        listed = listed if isinstance(listed, list) else [listed]
        if not any(isinstance(cb, LastCheckpoint) for cb in [*listed, *callbacks]):
            # last.ckpt beside best.ckpt (a --checkpoint.dirpath moves both); it runs after the best one
            best = next((cb for cb in callbacks if isinstance(cb, ModelCheckpoint)), None)
            callbacks = [*callbacks, LastCheckpoint(best.dirpath if best is not None else None)]
        if not any(isinstance(cb, EpochTimes) for cb in [*listed, *callbacks]):
            callbacks = [*callbacks, EpochTimes()]  # time/train_s and time/val_s per epoch in metrics.csv
        callbacks = [*callbacks, *getattr(self, "precision_notes", [])]
        has_bar = any(isinstance(cb, ProgressBar) for cb in [*listed, *callbacks])
        if config.get("enable_progress_bar", True) is not False and not has_bar:
            callbacks = [*callbacks, RichProgressBar()]
        return super()._instantiate_trainer(config, callbacks)


def _default_model(class_path: str) -> str:
    """The network a PolicyModule class path trains when ``model`` is not given."""
    name = class_path.rsplit(".", 1)[-1]
    return name if name in register_policy_classes() else PolicyModule.default_model


CONFIG_FLAGS = ("--config", "-c")


def _config_value(value: str) -> str:
    """A ``--config`` value: a path that exists as given, else the shipped config it names (``fit/vit_lstm``), else
    as given (LightningCLI reports it, or reads it as YAML text)."""
    if Path(value).exists():
        return value
    found = find_config(value)
    return str(found) if found is not None else value


def resolve_config_args(argv: list[str]) -> list[str]:
    """``argv`` with each ``--config``/``-c`` value resolved by ``_config_value``."""
    out = []
    for i, arg in enumerate(argv):
        if i > 0 and argv[i - 1] in CONFIG_FLAGS:
            arg = _config_value(arg)
        elif arg.startswith("--config="):
            arg = "--config=" + _config_value(arg.partition("=")[2])
        out.append(arg)
    return out


def build_cli(argv: list[str], run: bool = True) -> VitflyCLI:
    """The LightningCLI object for ``argv`` (``["fit", "--config", ...]``; a config by path or by the name of a
    shipped config, ``fit/vit_lstm``)."""
    argv = resolve_config_args(list(argv))
    register_policy_classes()  # makes ``model: <registered name>`` resolvable
    omegaconf = {"parser_mode": "omegaconf"}
    # argv is passed explicitly because `vitfly` strips nothing; Lightning warns when sys.argv is also set
    warnings.filterwarnings("ignore", message="LightningCLI's args parameter", category=UserWarning)
    return VitflyCLI(
        PolicyModule,
        TrajectoryDataModule,
        subclass_mode_model=True,
        auto_configure_optimizers=False,  # PolicyModule owns Adam and the warm-up schedule
        seed_everything_default=0,
        save_config_kwargs={"overwrite": True},
        parser_kwargs={**omegaconf, **{name: dict(omegaconf) for name in SUBCOMMANDS}},
        args=argv,
        run=run,
    )


def run_lightning_cli(argv: list[str]) -> int:
    """Run ``vitfly fit|validate|test|predict ...``; returns the exit status."""
    default_wandb_offline()
    try:
        build_cli(list(argv))
    except SystemExit as exit_:  # argument errors and --help
        code = exit_.code
        return code if isinstance(code, int) else (0 if code is None else 2)
    finally:
        finish_wandb()
    return 0
