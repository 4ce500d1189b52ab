"""`vitfly ablate --no-state`: config presets, the table beside the paper's numbers, and the tiny preset end to end."""

import json

import pytest

from vitfly.cli import main
from vitfly.eval.paper_tables import paper_success
from vitfly.workflows.ablation import AblationConfig, ablation_markdown, ablation_rows, load_ablation_config


def test_paper_numbers_are_the_papers_table():
    # spot checks against tables/table-no-state-info (success %, no state / with state)
    assert paper_success("spheres", "convnet", 3, False) == 27 and paper_success("spheres", "convnet", 3, True) == 63
    assert paper_success("spheres", "vit_lstm", 7, True) == 36
    assert paper_success("trees", "unet_lstm", 3, False) == 100
    assert paper_success("trees", "vit", 7, True) == 80
    assert paper_success("trees", "resnet18", 3, True) is None
    assert paper_success("spheres", "convnet", 4, True) is None


def test_tiny_preset_overrides_the_papers_protocol():
    paper = load_ablation_config("configs/ablate.yaml")
    assert paper.models == ["convnet", "lstmnet", "unet_lstm", "vit", "vit_lstm"]
    assert paper.train.max_epochs == 100 and paper.train.policy_kwargs["lr"] == 1e-4
    assert paper.evaluate.env == ["spheres", "trees"] and paper.evaluate.speeds == [3.0, 5.0, 7.0]
    tiny = load_ablation_config("configs/ablate.yaml", "tiny", {"models": ["convnet"]})
    assert tiny.train.max_epochs == 1 and tiny.train.policy_kwargs["lr"] == 1e-3
    assert tiny.evaluate.speeds == [3.0, 5.0, 7.0] and tiny.evaluate.trials == 2  # merged, not replaced
    assert tiny.collect["seed"] == 0 and tiny.collect["trajectories"] == 6 and tiny.evaluate.timeout_s == 5.0
    with pytest.raises(Exception, match="no preset 'huge'"):
        load_ablation_config("configs/ablate.yaml", "huge")


def test_ablation_table_pairs_runs_and_paper():
    cfg = AblationConfig(models=["convnet"])
    cfg.evaluate.env, cfg.evaluate.speeds = ["spheres"], [3.0, 5.0]
    summary = [
        {"policy": "convnet", "env": "spheres", "speed": 3.0, "success_paper_rate": 0.5, "trials": 4},
        {"policy": "convnet-nostate", "env": "spheres", "speed": 3.0, "success_paper_rate": 0.25, "trials": 4},
        {"policy": "convnet", "env": "spheres", "speed": 5.0, "success_paper_rate": 1.0, "trials": 4},
        {"policy": "expert", "env": "spheres", "speed": 3.0, "success_paper_rate": 1.0, "trials": 4},
    ]
    rows = ablation_rows(summary, cfg)
    assert rows[0] == {"env": "spheres", "model": "convnet", "speed": 3.0, "success_nostate": 0.25,
                       "trials_nostate": 4, "paper_nostate": 27, "success_state": 0.5, "trials_state": 4,
                       "paper_state": 63}
    assert rows[1]["success_nostate"] is None  # not flown (yet)
    md = ablation_markdown(rows, [3.0, 5.0])
    assert "| spheres | ConvNet | 25 (27) | 50 (63) | - (18) | 100 (54) |" in md
    assert "Success as the paper defines it: a trial without a collision." in md


def test_ablate_needs_the_ablation_flag(capsys):
    assert main(["ablate"]) == 2
    assert "--no-state" in capsys.readouterr().err


@pytest.mark.slow
def test_tiny_ablation_end_to_end(tmp_path, capsys):
    out = tmp_path / "ablate"
    args = ["ablate", "--no-state", "--preset", "tiny", "--out", str(out), "--data", str(tmp_path / "d.h5"),
            "--no-progress"]
    assert main(args) == 0
    text = capsys.readouterr().out
    assert "ConvNet" in text and "(63)" in text
    md = (out / "ablation.md").read_text()
    assert md.count("| ConvNet |") == 2  # spheres and trees
    recs = [json.loads(x) for x in (out / "eval" / "trials.jsonl").read_text().splitlines()]
    assert {r["policy"] for r in recs} == {"convnet", "convnet-nostate"}
    assert len(recs) == 2 * 2 * 3 * 2  # policies x envs x speeds x trials
    assert (out / "train" / "convnet-nostate" / "done.json").exists()
    # rerun: everything is done, nothing is flown or trained again
    assert main(args) == 0
    again = capsys.readouterr().out
    assert "0 trials flown" in again and "done before" in again
