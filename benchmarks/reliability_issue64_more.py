"""Issue 64's sixty new cases, of the same kinds as ``benchmarks/reliability_issue64.py``, on one tree.

    python benchmarks/reliability_issue64_more.py <source tree> <output.json>

The kinds: a successful command's exit status; inputs moved by ``--restart`` or written over; code or paths a
file could smuggle in (pickles, YAML tags, module names, class names, index paths); settings and files
trusted without checking; unbounded or late refusals; unclear errors on bad files and names. Each case runs
the tree's own code in a subprocess on fabricated inputs in a temporary folder (the helpers of
``reliability_issue64.py``: exit status, last error line, whether a watched input changed, case facts).
``RELIABILITY_THREADS`` sets each command's torch threads (default 2). About 6 minutes on 2 CPU cores.
Results: ``docs/results/reliability.md``.
"""

from __future__ import annotations

import json
import pickle
import shutil
import sys
from pathlib import Path

import numpy as np
import scipy.io
from PIL import Image

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # the repository root, for `benchmarks`
from benchmarks.reliability_issue64 import (  # noqa: E402
    OUTPUT,
    RESULTS,
    TMP,
    case,
    files_under,
    launcher,
    loads,
    pipeline_copy,
    python,
    run,
)

GENERATE = ["--pipeline", "sar-zero123/sim-prior-rotated", "--d_az", "30", "--num_inference_steps", "2"]
# fmt: off
SIMCLR_TINY = [
    "--image_size", "16", "--hidden_sizes", "8", "8", "8", "8", "--embedding_size", "8",
    "--projection_hidden_dim", "8", "--projection_dim", "4", "--global_batch_size", "4",
    "--monotonic_q", "16", "--report_to", "none",
]
VAE_TINY = [
    "--image_size", "32", "--block_out_channels", "8", "8", "--norm_num_groups", "4",
    "--layers_per_block", "1", "--train_batch_size", "4", "--report_to", "none",
    "--num_scaling_batches", "2", "--num_eval_images", "2",
]
# fmt: on
#: A pickle that runs code when loaded: it creates this file.
PWNED = TMP / "pwned"


class _Payload:
    def __reduce__(self):
        return (exec, (f"open({str(PWNED)!r}, 'w').write('ran')",))


def ran_code() -> dict:
    return {"code_ran": PWNED.exists()}


def sealed_pipeline(name: str, edit) -> Path:
    """A copy of the bundled prior with one file edited by ``edit(folder)``."""
    folder = pipeline_copy(name)
    edit(folder)
    return folder


def edit_json(path: Path, **changes) -> None:
    path.write_text(json.dumps({**json.loads(path.read_text()), **changes}))


def load(folder: Path, extra: str = "") -> dict:
    return python(
        "from sar_zero123 import SARZero123Pipeline\n"
        f"SARZero123Pipeline.from_pretrained({str(folder)!r}{extra})\n"
    )


def generate(image: Path, out: str, *extra: str, pipeline: str | None = None, timeout: float = 300) -> dict:
    argv = [*GENERATE, "--image", str(image), "--output_dir", str(TMP / out), *extra]
    if pipeline is not None:
        argv[1] = pipeline
    return launcher("sar-zero123-generate", argv, timeout=timeout)


def write_index_rows(folder: Path, edit, first_only: bool = False) -> None:
    """``folder/index.csv`` with ``edit(header, row)`` applied to each row (lists of strings) or the first."""
    lines = (folder / "index.csv").read_text().splitlines()
    header = lines[0].split(",")
    rows = [line.split(",") for line in lines[1:]]
    for row in rows[:1] if first_only else rows:
        edit(header, row)
    (folder / "index.csv").write_text("\n".join([lines[0], *[",".join(r) for r in rows]]) + "\n")


def main() -> None:  # noqa: PLR0915 - one case after another
    rng = np.random.default_rng(1)
    chip = TMP / "chip.png"
    Image.fromarray((rng.random((64, 64)) * 80 + 20 * np.eye(64)).astype(np.uint8)).save(chip)
    data = TMP / "data"
    sim = ["--classes", "TANK", "APC", "--instances", "1", "--azimuth_step_deg", "60", "--size", "64"]
    run(["train/simulate.py", "--out", str(data), *sim, "--depressions_deg", "15", "17"])

    def data_copy(name: str) -> Path:
        shutil.copytree(data, TMP / name)
        return TMP / name

    augment = ["--d_az", "30", "--num_inference_steps", "2"]
    small_sim = ["--classes", "TANK", "--instances", "1", "--azimuth_step_deg", "180",
                 "--depressions_deg", "17", "--size", "32"]  # fmt: skip

    # 1. a successful command exits 0 and prints its output folder
    case(
        "1. sar-zero123-simulate succeeds",
        lambda: launcher(
            "sar-zero123-simulate",
            ["--out", str(TMP / "sim_ok"), *small_sim],
        ),
    )
    case(
        "1. sar-zero123-augment succeeds",
        lambda: launcher(
            "sar-zero123-augment",
            ["--data", str(data), "--out", str(TMP / "aug_ok"), *augment, "--max_chips_per_class", "1"],
        ),
    )
    case(
        "1. sar-zero123-simclr succeeds (1 step)",
        lambda: launcher(
            "sar-zero123-simclr",
            [
                "--data",
                str(data),
                "--output_dir",
                str(TMP / "simclr_ok"),
                "--max_train_steps",
                "1",
                "--checkpointing_steps",
                "1",
                *SIMCLR_TINY,
            ],
        ),
    )
    case(
        "1. sar-zero123-vae succeeds (1 step)",
        lambda: launcher(
            "sar-zero123-vae",
            [
                "--data",
                str(data),
                "--output_dir",
                str(TMP / "vae_ok"),
                "--max_train_steps",
                "1",
                "--checkpointing_steps",
                "1",
                *VAE_TINY,
            ],
        ),
    )
    case(
        "1. sar-zero123-interpolate succeeds",
        lambda: launcher(
            "sar-zero123-interpolate",
            [
                "--start",
                "sar-zero123/sim-prior-rotated",
                "--finetuned",
                str(pipeline_copy("interp_ok_in")),
                "--output_dir",
                str(TMP / "interp_ok"),
                "--alpha",
                "0.5",
            ],
        ),
    )
    case("1. sar-zero123-generate --help exits 0", lambda: launcher("sar-zero123-generate", ["--help"]))
    case(
        "1. a refusal exits 2, not 1 (vae --learning_rate -1)",
        lambda: launcher(
            "sar-zero123-vae",
            ["--data", str(data), "--output_dir", str(TMP / "vae_bad"), "--learning_rate", "-1"],
        ),
    )
    case(
        "1. a resumed run that is already complete exits 0 (simclr --resume)",
        lambda: launcher(
            "sar-zero123-simclr",
            [
                "--data",
                str(data),
                "--output_dir",
                str(TMP / "simclr_ok"),
                "--max_train_steps",
                "1",
                "--checkpointing_steps",
                "1",
                *SIMCLR_TINY,
                "--resume",
            ],
        ),
    )

    # 2. inputs never moved or changed, either way round, links and bundled names resolved
    for name, command, argv_of in [
        (
            "finetune --data D --output_dir D/chips --restart",
            "sar-zero123-finetune",
            lambda d: ["--data", str(d), "--output_dir", str(d / "chips"), "--encoder", str(d), "--restart"],
        ),
        (
            "simclr --data D --output_dir D --restart",
            "sar-zero123-simclr",
            lambda d: ["--data", str(d), "--output_dir", str(d), "--restart", *SIMCLR_TINY],
        ),
        (
            "vae --data D --output_dir D/chips --restart",
            "sar-zero123-vae",
            lambda d: ["--data", str(d), "--output_dir", str(d / "chips"), "--restart", *VAE_TINY],
        ),
        (
            "evaluators --data D --output_dir D --restart",
            "sar-zero123-evaluators",
            lambda d: ["--data", str(d), "--output_dir", str(d), "--restart"],
        ),
        (
            "augment --data D --out D --restart",
            "sar-zero123-augment",
            lambda d: ["--data", str(d), "--out", str(d), *augment, "--restart"],
        ),
        (
            "augment --data D/chips/.. --out D/x --restart (a path through ..)",
            "sar-zero123-augment",
            lambda d: ["--data", str(d / "chips" / ".."), "--out", str(d / "x"), *augment, "--restart"],
        ),
        (
            "evaluate --data D --output_dir D/chips --restart",
            "sar-zero123-evaluate",
            lambda d: [
                "--pipeline",
                "sar-zero123/sim-prior-rotated",
                "--evaluators",
                str(d),
                "--data",
                str(d),
                "--output_dir",
                str(d / "chips"),
                "--restart",
            ],
        ),
    ]:
        folder = data_copy(f"restart_{len(RESULTS)}")
        argv = argv_of(folder)
        # what the input holds: its index and chips (an output beside them is not a change to them)
        held = [folder / "index.csv", folder / "chips"]
        case(f"2. {name}", lambda c=command, a=argv: launcher(c, a), watch=held)
    link_target = data_copy("restart_link")
    (TMP / "link_to_data").symlink_to(link_target, target_is_directory=True)
    case(
        "2. augment --out <a symlink to its data> --restart",
        lambda: launcher(
            "sar-zero123-augment",
            ["--data", str(link_target), "--out", str(TMP / "link_to_data"), *augment, "--restart"],
        ),
        watch=[link_target],
    )
    tuned = pipeline_copy("interp_restart")
    case(
        "2. interpolate --finetuned F --output_dir F/unet --restart",
        lambda: launcher(
            "sar-zero123-interpolate",
            [
                "--start",
                "sar-zero123/sim-prior-rotated",
                "--finetuned",
                str(tuned),
                "--output_dir",
                str(tuned / "unet"),
                "--restart",
            ],
        ),
        watch=[tuned],
        facts=lambda: loads(tuned),
    )
    tuned_same = pipeline_copy("interp_same")
    case(
        "2. interpolate --output_dir <its --finetuned folder> --restart",
        lambda: launcher(
            "sar-zero123-interpolate",
            [
                "--start",
                "sar-zero123/sim-prior-rotated",
                "--finetuned",
                str(tuned_same),
                "--output_dir",
                str(tuned_same),
                "--restart",
            ],
        ),
        watch=[tuned_same],
        facts=lambda: loads(tuned_same),
    )
    image_dir = TMP / "image_dir"
    image_dir.mkdir()
    shutil.copy(chip, image_dir / "chip.png")
    case(
        "2. generate --image D/chip.png --output_dir D --restart",
        lambda: launcher(
            "sar-zero123-generate",
            [*GENERATE, "--image", str(image_dir / "chip.png"), "--output_dir", str(image_dir), "--restart"],
        ),
        watch=[image_dir],
    )
    notes = TMP / "my_notes"
    notes.mkdir()
    (notes / "thesis.txt").write_text("not a run\n")
    case(
        "2. generate --output_dir <a user's folder that is not a run> --restart",
        lambda: generate(chip, "my_notes", "--restart"),
        watch=[notes],
    )
    other_run = TMP / "other_command_run"
    launcher(
        "sar-zero123-simulate",
        ["--out", str(other_run), *small_sim],
    )
    case(
        "2. generate --output_dir <a simulate folder, a dataset> --restart",
        lambda: generate(chip, "other_command_run", "--restart"),
        watch=[other_run],
    )
    pipe_out = pipeline_copy("pipe_as_out")
    case(
        "2. generate --output_dir <a pipeline folder, not its own> --restart",
        lambda: generate(chip, "pipe_as_out", "--restart"),
        watch=[pipe_out],
    )
    case(
        "2. generate --output_dir <the installed package's pretrained folder>",
        lambda: launcher(
            "sar-zero123-generate",
            [
                *GENERATE,
                "--image",
                str(chip),
                "--output_dir",
                str(Path(__file__).resolve().parents[1] / "sar_zero123" / "pretrained" / "views"),
            ],
        ),
        facts=lambda: {
            "written_into_package": (
                Path(__file__).resolve().parents[1] / "sar_zero123" / "pretrained" / "views"
            ).exists()
        },
    )
    shutil.rmtree(Path(__file__).resolve().parents[1] / "sar_zero123" / "pretrained" / "views", True)

    # 3. security: pickles, YAML tags, module and class names, index paths
    # a run killed after its first checkpoint (run.json unfinished), its checkpoint then crafted: a pickle in
    # place of a state file, and the checkpoint's manifest left as it was or sealed again over the pickle
    stopped = TMP / "simclr_stopped"
    simclr_args = ["--data", str(data), "--max_train_steps", "3", "--checkpointing_steps", "1", *SIMCLR_TINY]
    launcher(
        "sar-zero123-simclr", [*simclr_args, "--output_dir", str(stopped), "--max_train_minutes", "1e-9"]
    )
    record = json.loads((stopped / "run.json").read_text())
    (stopped / "run.json").write_text(json.dumps({**record, "finished": False}))
    crafted = [("random_states_0.pkl", False), ("random_states_0.pkl", True), ("optimizer.bin", True),
               ("custom_checkpoint_0.pkl", True)]  # fmt: skip
    for victim, reseal in crafted:
        crashed = TMP / f"resume_{victim.split('.')[0]}_{reseal}"
        shutil.copytree(stopped, crashed)
        with open(crashed / "checkpoint-1" / victim, "wb") as handle:
            pickle.dump(_Payload(), handle)
        if reseal:
            python(f"from sar_zero123.runs.manifest import write_manifest; "
                   f"write_manifest({str(crashed / 'checkpoint-1')!r})")  # fmt: skip
        sealed = "its manifest sealed again over it" if reseal else "its manifest as it was"
        case(
            f"3. simclr --resume onto a checkpoint whose {victim} is a crafted pickle, {sealed}",
            lambda c=crashed: launcher(
                "sar-zero123-simclr",
                [*simclr_args, "--output_dir", str(c), "--max_train_minutes", "1e-9", "--resume"],
            ),
            facts=ran_code,
        )
        PWNED.unlink(missing_ok=True)
    pickled_npy = TMP / "pickled.npy"
    np.save(pickled_npy, np.array([_Payload()], dtype=object), allow_pickle=True)
    case(
        "3. generate --image <an .npy holding a pickled object>",
        lambda: generate(pickled_npy, "npy_pickle"),
        facts=ran_code,
    )
    PWNED.unlink(missing_ok=True)
    tag = TMP / "tag.yaml"
    tag.write_text(f"seed: !!python/object/apply:os.system ['touch {PWNED}']\n")
    case(
        "3. generate --config <a YAML file with a python tag>",
        lambda: generate(chip, "yaml_tag", "--config", str(tag)),
        facts=ran_code,
    )
    recipe_tag = TMP / "recipe_tag.yaml"
    recipe_tag.write_text(f"simclr:\n  seed: !!python/object/apply:os.system ['touch {PWNED}']\n")
    case(
        "3. quickstart --recipe <a recipe with a python tag>",
        lambda: launcher(
            "sar-zero123-quickstart", ["--output_dir", str(TMP / "qs_tag"), "--recipe", str(recipe_tag)]
        ),
        facts=ran_code,
    )
    recipe_escape = TMP / "recipe_escape.yaml"
    recipe_escape.write_text("extends: ../../../etc/passwd\n")
    case(
        "3. quickstart --recipe <a recipe that extends a path outside the package>",
        lambda: launcher(
            "sar-zero123-quickstart", ["--output_dir", str(TMP / "qs_ext"), "--recipe", str(recipe_escape)]
        ),
    )
    big_recipe = TMP / "big_recipe.yaml"
    big_recipe.write_text("# " + "x" * 200_000 + "\nsimclr: {}\n")
    case(
        "3. quickstart --recipe <a 200 kB recipe>",
        lambda: launcher(
            "sar-zero123-quickstart", ["--output_dir", str(TMP / "qs_big"), "--recipe", str(big_recipe)]
        ),
    )
    for label, entry in [
        ("['os', 'system']", ["os", "system"]),
        ("['subprocess', 'Popen']", ["subprocess", "Popen"]),
        ("['diffusers', 'StableDiffusionPipeline'] as its unet", None),
    ]:

        def edit(folder: Path, entry=entry) -> None:
            index = json.loads((folder / "model_index.json").read_text())
            if entry is None:
                index["unet"] = ["diffusers", "StableDiffusionPipeline"]
            else:
                index["extra"] = entry
            (folder / "model_index.json").write_text(json.dumps(index))

        folder = sealed_pipeline(f"module_{len(RESULTS)}", edit)
        case(
            f"3. a model_index.json naming {label} (manifest check off)",
            lambda f=folder: load(f, ", verify_manifest=False"),
            facts=ran_code,
        )
    odd = sealed_pipeline(
        "scheduler_class",
        lambda f: edit_json(f / "scheduler" / "scheduler_config.json", _class_name="FlaxDDIMScheduler"),
    )
    case(
        "3. a scheduler config naming a class outside the allow-list (manifest check off)",
        lambda: load(odd, ", verify_manifest=False"),
    )
    for label, value in [
        ("an absolute path (/tmp/abs_escape)", str(TMP / "abs_escape")),
        ("'..'", ".."),
        ("'a/b'", "a/b"),
        ("'.'", "."),
        ("an empty name", ""),
    ]:
        escape = data_copy(f"class_{len(RESULTS)}")
        write_index_rows(
            escape, lambda header, row, v=value: row.__setitem__(header.index("target_class"), v)
        )
        case(
            f"3. augment: a target_class that is {label}",
            lambda e=escape: launcher(
                "sar-zero123-augment", ["--data", str(e), "--out", str(TMP / (e.name + "_o")), *augment]
            ),
            watch=[escape],
            facts=lambda: {"abs_escape_written": (TMP / "abs_escape").exists()},
        )
    outside = TMP / "secret.png"
    shutil.copy(chip, outside)
    for label, path in [
        ("an absolute path outside it", str(outside)),
        ("a ../ path outside it", "../secret.png"),
    ]:
        escape = data_copy(f"path_{len(RESULTS)}")
        write_index_rows(escape, lambda header, row, p=path: row.__setitem__(header.index("path"), p), True)
        # an index may name chips stored elsewhere (augment's own output lists the real chips it keeps by
        # their path): the chip is read, and nothing is written beside it or anywhere but --out
        before = files_under(TMP)
        case(
            f"3. augment: an index.csv row whose chip path is {label} (read; written only into --out)",
            lambda e=escape: launcher(
                "sar-zero123-augment", ["--data", str(e), "--out", str(TMP / (e.name + "_o")), *augment]
            ),
            watch=[outside],
            facts=lambda e=escape, b=before: {
                "written_outside_out": any(
                    not f.startswith((e.name + "_o", f".{e.name}_o.lock")) for f in files_under(TMP) - b
                )
            },
        )

    def list_outside(folder: Path) -> None:
        files = json.loads((folder / "manifest.json").read_text())["files"]
        entry = {"bytes": outside.stat().st_size, "sha256": "0" * 64}
        edit_json(folder / "manifest.json", files={**files, "../secret.png": entry})

    manifest_escape = sealed_pipeline("manifest_escape", list_outside)
    case("3. a pipeline manifest listing a file outside the pipeline", lambda: load(manifest_escape))

    # 4. trusted without checking
    for label, edit in [
        (
            "a scheduler num_train_timesteps of 10",
            lambda f: edit_json(f / "scheduler" / "scheduler_config.json", num_train_timesteps=10),
        ),
        (
            "a VAE scaling_factor of 1000",
            lambda f: edit_json(f / "vae" / "config.json", scaling_factor=1000.0),
        ),
        (
            "its recorded guidance_scale of 1e9",
            lambda f: edit_json(
                f / "model_index.json",
                sampler={
                    **json.loads((f / "model_index.json").read_text()).get("sampler", {}),
                    "guidance_scale": 1e9,
                },
            ),
        ),
        (
            "its recorded num_inference_steps of 10**7",
            lambda f: edit_json(
                f / "model_index.json",
                sampler={
                    **json.loads((f / "model_index.json").read_text()).get("sampler", {}),
                    "num_inference_steps": 10**7,
                },
            ),
        ),
        (
            "a decibel_scaling.json with min_db > max_db",
            lambda f: edit_json(f / "decibel_scaling.json", min_db=10.0, max_db=0.0),
        ),
        (
            "a VAE weight file replaced by another's",
            lambda f: shutil.copy(
                f / "unet" / "diffusion_pytorch_model.safetensors",
                f / "vae" / "diffusion_pytorch_model.safetensors",
            ),
        ),
        ("an extra unlisted file in unet/", lambda f: (f / "unet" / "extra.safetensors").write_bytes(b"x")),
        ("a manifest.json that is not JSON", lambda f: (f / "manifest.json").write_text("{not json")),
        (
            "an image_encoder config with another hidden size",
            lambda f: edit_json(f / "image_encoder" / "config.json", embedding_size=7),
        ),
    ]:
        folder = sealed_pipeline(f"trusted_{len(RESULTS)}", edit)
        # values no check of the files catches: loaded with the manifest check off, they are still refused
        extra = ", verify_manifest=False" if "recorded" in label else ""
        case(
            f"4. a pipeline with {label}{' (manifest check off)' if extra else ''}",
            lambda f=folder, e=extra: load(f, e),
        )
    unsealed = sealed_pipeline("no_manifest", lambda f: (f / "manifest.json").unlink())
    case("4. a pipeline without a manifest (an older export)", lambda: load(unsealed))
    liar = data_copy("liar")
    for chip_file in sorted(liar.rglob("*.npy")):  # the simulator's chips: 64 px arrays, cut to 16 px
        np.save(chip_file, np.load(chip_file)[:16, :16])
    case(
        "4. augment on 16 px chips whose index says 64",
        lambda: launcher(
            "sar-zero123-augment", ["--data", str(liar), "--out", str(TMP / "liar_out"), *augment]
        ),
    )
    nan_index = data_copy("nan_index")
    write_index_rows(nan_index, lambda header, row: row.__setitem__(header.index("azimuth_deg"), "nan"))
    case(
        "4. augment on an index.csv with azimuth nan",
        lambda: launcher(
            "sar-zero123-augment", ["--data", str(nan_index), "--out", str(TMP / "nan_out"), *augment]
        ),
    )
    case(
        "4. prior --init <a prior> --model_size small (its size is the init's)",
        lambda: launcher(
            "sar-zero123-prior",
            [
                "--init",
                "sar-zero123/sim-prior-rotated",
                "--model_size",
                "small",
                "--output_dir",
                str(TMP / "prior_init"),
                "--base_steps",
                "1",
            ],
            timeout=120,
        ),
    )

    # 5. unbounded or late
    case(
        "5. generate --num_inference_steps 10000000",
        lambda: generate(chip, "steps_huge", "--num_inference_steps", "10000000", timeout=60),
    )
    case(
        "5. generate with 5,000 requested azimuths",
        lambda: launcher(
            "sar-zero123-generate",
            [
                *GENERATE[:2],
                "--image",
                str(chip),
                "--d_az",
                *[str(v % 360) for v in range(5000)],
                "--num_inference_steps",
                "2",
                "--output_dir",
                str(TMP / "many"),
            ],
            timeout=60,
        ),
    )
    ev = ["--pipeline", "sar-zero123/sim-prior-rotated", "--evaluators", str(data), "--data", str(data)]
    for name, script, argv in [
        ("simulate --size 100000", "simulate", ["--out", str(TMP / "sim_huge"), "--size", "100000"]),
        ("simulate --instances 1000000 --azimuth_step_deg 0.01", "simulate",
         ["--out", str(TMP / "sim_many"), "--instances", "1000000", "--azimuth_step_deg", "0.01"]),
        ("evaluate --n 1000000000", "evaluate",
         [*ev, "--n", "1000000000", "--output_dir", str(TMP / "ev_n")]),
    ]:  # fmt: skip
        case(f"5. {name}", lambda s=script, a=argv: launcher(f"sar-zero123-{s}", a, timeout=60))
    case(
        "5. quickstart --set an unknown field (refused before any stage)",
        lambda: launcher(
            "sar-zero123-quickstart",
            ["--output_dir", str(TMP / "qs_unknown"), "--set", "finetune.no_such_field=1"],
            timeout=60,
        ),
        facts=lambda: {"stages_started": sorted(files_under(TMP / "qs_unknown"))[:5]},
    )
    case(
        "5. finetune --image_size 30 (refused before loading anything)",
        lambda: launcher(
            "sar-zero123-finetune",
            [
                "--data",
                str(data),
                "--output_dir",
                str(TMP / "ft30"),
                "--image_size",
                "30",
                "--encoder",
                str(data),
            ],
            timeout=60,
        ),
    )

    # 6. unclear errors on bad files and names
    empty = TMP / "empty.png"
    empty.write_bytes(b"")
    text = TMP / "text.png"
    text.write_text("hello, not a PNG\n")
    rgba = TMP / "rgba.png"
    Image.fromarray((rng.random((64, 64, 4)) * 255).astype(np.uint8), "RGBA").save(rgba)
    deep = TMP / "deep.png"
    Image.fromarray((rng.random((64, 64)) * 65535).astype(np.uint16)).save(deep)
    nan_npy = TMP / "nan.npy"
    np.save(nan_npy, np.full((64, 64), np.nan, dtype=np.float32))
    complex_npy = TMP / "complex.npy"
    np.save(complex_npy, (rng.random((64, 64)) + 1j * rng.random((64, 64))).astype(np.complex64))
    cube = TMP / "cube.mat"
    scipy.io.savemat(cube, {"chip": rng.random((4, 64, 64))})
    tiny = TMP / "tiny.png"
    Image.fromarray((rng.random((4, 4)) * 255).astype(np.uint8)).save(tiny)
    for label, image in [
        ("an empty file", empty),
        ("a text file named .png", text),
        ("a folder", TMP),
        ("a missing file", TMP / "missing.png"),
        ("an RGBA PNG", rgba),
        ("a 16-bit PNG", deep),
        ("an .npy of NaN", nan_npy),
        ("a complex .npy", complex_npy),
        ("a .mat holding a 3-D array", cube),
        ("a 4 x 4 PNG", tiny),
    ]:
        case(f"6. generate --image <{label}>", lambda i=image: generate(i, f"bad_{len(RESULTS)}"))
    not_a_pipeline = TMP / "empty_pipeline"
    not_a_pipeline.mkdir()
    broken_index = sealed_pipeline("broken_index", lambda f: (f / "model_index.json").write_text("{oops"))
    for label, pipeline in [
        ("an empty folder", str(not_a_pipeline)),
        ("a file", str(chip)),
        ("a folder whose model_index.json is not JSON", str(broken_index)),
        ("'../sar-zero123/sim-prior-rotated'", "../sar-zero123/sim-prior-rotated"),
    ]:
        case(
            f"6. generate --pipeline <{label}>",
            lambda p=pipeline: generate(chip, f"badpipe_{len(RESULTS)}", pipeline=p),
        )
    no_index = TMP / "no_index"
    no_index.mkdir()
    header_only = data_copy("header_only")
    lines = (header_only / "index.csv").read_text().splitlines()
    (header_only / "index.csv").write_text(lines[0] + "\n")
    missing_column = data_copy("missing_column")
    (missing_column / "index.csv").write_text(
        "\n".join(
            ",".join(
                cell
                for k, cell in enumerate(line.split(","))
                if k != lines[0].split(",").index("azimuth_deg")
            )
            for line in (missing_column / "index.csv").read_text().splitlines()
        )
        + "\n"
    )
    for label, folder in [
        ("a folder without index.csv", no_index),
        ("an index.csv with no rows", header_only),
        ("an index.csv without azimuth_deg", missing_column),
    ]:
        case(
            f"6. augment --data <{label}>",
            lambda d=folder: launcher(
                "sar-zero123-augment", ["--data", str(d), "--out", str(TMP / f"aug_{len(RESULTS)}"), *augment]
            ),
        )
    case(
        "6. quickstart --recipe <an unknown name>",
        lambda: launcher(
            "sar-zero123-quickstart", ["--output_dir", str(TMP / "qs_name"), "--recipe", "fastest"]
        ),
    )
    case(
        "6. quickstart --set <no '='>",
        lambda: launcher(
            "sar-zero123-quickstart", ["--output_dir", str(TMP / "qs_eq"), "--set", "finetune.pfm_weight"]
        ),
    )
    case(
        "6. simclr --resume_from_checkpoint <an empty folder>",
        lambda: launcher(
            "sar-zero123-simclr",
            [
                "--data",
                str(data),
                "--output_dir",
                str(TMP / "simclr_empty"),
                "--resume_from_checkpoint",
                str(not_a_pipeline),
                *SIMCLR_TINY,
            ],
        ),
    )
    case(
        "6. generate --config <a missing file>",
        lambda: generate(chip, "cfg_missing", "--config", str(TMP / "nope.yaml")),
    )
    OUTPUT.parent.mkdir(parents=True, exist_ok=True)
    OUTPUT.write_text(json.dumps({"tree": "new cases", "cases": RESULTS}, indent=1) + "\n")
    shutil.rmtree(TMP, ignore_errors=True)
    print(markdown_table(RESULTS))


def markdown_table(results: dict[str, dict]) -> str:
    """One row per case: exit status, the refusal or the output's last line (cut at 130 characters), facts."""
    rows = ["| case | outcome |", "| --- | --- |"]
    for name, r in results.items():
        said = r.get("error") or (f"prints {r['stdout_last_line']}" if r.get("stdout_last_line") else "")
        parts = [f"rc {r['rc']}", said[:130] + ("…" if len(said) > 130 else "")]
        parts += [f"{key.replace('_', ' ')}: {'yes' if value else 'no'}" for key, value in r.items()
                  if isinstance(value, bool) and key != "traceback"]  # fmt: skip
        cell = "; ".join(part for part in parts if part).replace("|", "\\|")
        rows.append(f"| {name.replace('|', '/')} | {cell} |")
    return "\n".join(rows)


if __name__ == "__main__":
    main()
