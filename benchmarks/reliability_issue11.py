"""Issue 11 (no silent failures): feed bad inputs to one source tree and print the outcome of each.

    python benchmarks/reliability_issue11.py <source tree> <output.json>

``<source tree>`` is a checkout of this repository (``.`` for this one; for the state before issue 11:
``git archive ccb1202 | tar -x -C /tmp/before``). Each case prints ``name<TAB>outcome``: what it
returned, or the exception type and the start of its message, plus the first warning of the project.
Uses the tiny test components (``tests/dummies.py``) and fabricated data in a temporary folder: about
a minute on 2 CPU cores. Results: ``docs/results/reliability.md``.
"""

import importlib
import json
import shutil
import sys
import tempfile
import warnings
from pathlib import Path

ROOT = Path(sys.argv[1]).resolve()
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "tests"))

import numpy as np  # noqa: E402
import PIL.Image  # noqa: E402
import torch  # noqa: E402
from accelerate.state import AcceleratorState, GradientState  # noqa: E402

from sar_zero123.data import ChipRecord, DecibelScaling, load_index, read_mstar_raw, write_index  # noqa: E402
from sar_zero123.data.splits import split_records  # noqa: E402

TMP = Path(tempfile.mkdtemp())
RESULTS = {}


def load(name):
    """`train.<name>` of the source tree (a namespace package in trees older than `train/__init__.py`)."""
    return importlib.import_module(f"train.{name}")


def attempt(name, fn):
    AcceleratorState._reset_state(True)
    GradientState._reset_state()
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        try:
            value = fn()
            outcome = f"returned {value}" if value is not None else "returned"
        except BaseException as error:  # noqa: BLE001
            outcome = f"{type(error).__name__}: {str(error)[:160]}"
    # the project's warnings (UserWarning; RuntimeWarning of numpy), not third-party deprecations
    ours = [str(w.message)[:120] for w in caught if issubclass(w.category, (UserWarning, RuntimeWarning))]
    if ours:
        outcome += f" | warning: {ours[0]}"
    RESULTS[name] = outcome.replace("\n", " ")
    print(f"{name}\t{RESULTS[name]}", flush=True)


# --- data
rng = np.random.default_rng(0)


def chips(root, classes=("A", "B"), depressions=(15.0, 17.0), n=6, size=32):
    root.mkdir(parents=True, exist_ok=True)
    records = []
    for c in classes:
        for d in depressions:
            for k in range(n):
                path = root / f"{c}_{d:g}_{k}.npy"
                np.save(path, rng.random((size, size), dtype=np.float32))
                records.append(ChipRecord(path, c, "s1", d, 60.0 * k))
    write_index(records, root)
    return root


DATA = chips(TMP / "data")
from sar_zero123.encoder import SAREncoder, SAREncoderConfig  # noqa: E402

torch.manual_seed(0)
ENC = SAREncoder(
    SAREncoderConfig(image_size=32, depths=(1,), hidden_sizes=(8,), embedding_size=8)
).save_pretrained(TMP / "enc")


def ft_args(out, *extra):
    return [
        "--output_dir",
        str(out),
        "--size",
        "tiny",
        "--data",
        str(DATA),
        "--encoder",
        str(ENC),
        "--train_batch_size",
        "2",
        "--report_to",
        "none",
        "--validation_steps",
        "0",
        *extra,
    ]


ft = load("finetune_pfm")


def diverge_ft():
    out = ft.main(
        ft_args(
            TMP / "ft_div", "--learning_rate", "1e30", "--max_train_steps", "4", "--checkpointing_steps", "2"
        )
    )
    from sar_zero123.model.pipeline import SARZero123Pipeline

    pipe = SARZero123Pipeline.from_pretrained(out / "pipeline")
    finite = all(torch.isfinite(p).all() for p in pipe.unet.parameters())
    return f"rc 0, exported pipeline with finite UNet weights: {finite}"


attempt("finetune --learning_rate 1e30", diverge_ft)


def ft_resume_lr():
    ft.main(
        ft_args(TMP / "ft_res", "--max_train_steps", "1", "--checkpointing_steps", "1", "--no-save_pipeline")
    )
    AcceleratorState._reset_state(True)
    GradientState._reset_state()
    ft.main(
        ft_args(
            TMP / "ft_res",
            "--max_train_steps",
            "2",
            "--checkpointing_steps",
            "1",
            "--no-save_pipeline",
            "--learning_rate",
            "0.5",
            "--resume_from_checkpoint",
            "latest",
        )
    )
    return "config.json learning_rate=" + str(
        json.loads((TMP / "ft_res" / "config.json").read_text())["learning_rate"]
    )


attempt("finetune resume with --learning_rate 0.5", ft_resume_lr)


def ft_truncated_latest():
    out = TMP / "ft_res"
    newest = sorted(out.glob("checkpoint-*"))[-1] / "model.safetensors"
    newest.write_bytes(newest.read_bytes()[:-100])
    ft.main(
        ft_args(
            out,
            "--max_train_steps",
            "3",
            "--checkpointing_steps",
            "1",
            "--no-save_pipeline",
            "--resume_from_checkpoint",
            "latest",
        )
    )


attempt("finetune resume latest, newest checkpoint truncated", ft_truncated_latest)


def ft_out_file():
    (TMP / "afile").write_text("x")
    ft.main(ft_args(TMP / "afile", "--max_train_steps", "1"))


attempt("finetune --output_dir <a file>", ft_out_file)

sc = load("pretrain_simclr")
# pretrain_simclr's global batch flag: --batch_size before issue 12, --global_batch_size since
SC_BATCH = "--global_batch_size" if hasattr(sc.PretrainSimCLRConfig, "global_batch_size") else "--batch_size"
SC = [
    "--data",
    str(DATA),
    "--report_to",
    "none",
    "--image_size",
    "16",
    "--hidden_sizes",
    "8",
    "8",
    "8",
    "8",
    "--embedding_size",
    "8",
    "--projection_hidden_dim",
    "8",
    "--projection_dim",
    "4",
    "--monotonic_q",
    "16",
]
attempt(
    "simclr --learning_rate 1e30",
    lambda: (
        "final_loss "
        + str(
            sc.main(
                [
                    *SC,
                    "--output_dir",
                    str(TMP / "sc1"),
                    SC_BATCH,
                    "4",
                    "--max_train_steps",
                    "4",
                    "--learning_rate",
                    "1e30",
                ]
            )["final_loss"]
        )
    ),
)
attempt(
    "simclr --batch_size 1",
    lambda: (
        "final_loss "
        + str(
            sc.main([*SC, "--output_dir", str(TMP / "sc2"), SC_BATCH, "1", "--max_train_steps", "2"])[
                "final_loss"
            ]
        )
    ),
)


def sc_resume():
    sc.main(
        [
            *SC,
            "--output_dir",
            str(TMP / "sc3"),
            SC_BATCH,
            "4",
            "--max_train_steps",
            "2",
            "--checkpointing_steps",
            "1",
        ]
    )
    sc.main(
        [
            *SC,
            "--output_dir",
            str(TMP / "sc3"),
            SC_BATCH,
            "4",
            "--max_train_steps",
            "2",
            "--learning_rate",
            "0.5",
            "--resume_from_checkpoint",
            "latest",
        ]
    )
    return "config.json learning_rate=" + str(
        json.loads((TMP / "sc3" / "config.json").read_text())["learning_rate"]
    )


attempt("simclr resume with --learning_rate 0.5", sc_resume)

vae = load("train_vae")
VAE = [
    "--data",
    str(DATA),
    "--image_size",
    "32",
    "--block_out_channels",
    "8",
    "8",
    "--norm_num_groups",
    "4",
    "--layers_per_block",
    "1",
    "--train_batch_size",
    "4",
    "--report_to",
    "none",
    "--num_scaling_batches",
    "2",
]
attempt(
    "train_vae --learning_rate 1e30",
    lambda: vae.main(
        [*VAE, "--output_dir", str(TMP / "vae"), "--max_train_steps", "4", "--learning_rate", "1e30"]
    ),
)

# --- MSTAR raw
from test_data_mstar_raw import write_mstar  # noqa: E402

mag = rng.rayleigh(0.1, size=(6, 5)).astype(np.float32)
phase = rng.uniform(0, 6.28, (6, 5)).astype(np.float32)


def raw_cut():
    p = write_mstar(TMP / "cut.000", mag, phase)
    p.write_bytes(p.read_bytes()[:-1])
    return f"phase is None: {read_mstar_raw(p).phase is None}"


def raw_rows():
    p = write_mstar(TMP / "rows.000", mag, phase)
    t = p.read_bytes()
    i = t.index(b"NumberOfRows= ") + len(b"NumberOfRows= ")
    p.write_bytes(t[:i] + b"3" + t[i + 1 :])
    return f"magnitude shape {read_mstar_raw(p).magnitude.shape}"


attempt("read_mstar_raw: file cut by 1 byte", raw_cut)
attempt("read_mstar_raw: NumberOfRows edited 6 -> 3", raw_rows)


def raw_empty_type():
    folder = TMP / "rawempty"
    folder.mkdir()
    write_mstar(folder / "HB1.000", mag, phase, fields={"TargetType": ""})
    load_index(folder)


attempt("raw folder with empty TargetType", raw_empty_type)


def raw_cache():
    folder = TMP / "rawcache"
    folder.mkdir()
    write_mstar(folder / "HB1.000", mag, phase)
    load_index(folder)
    write_mstar(folder / "HB2.000", mag, phase, fields={"TargetAz": "20"})
    return f"{len(load_index(folder))} of 2 chips listed"


attempt("raw folder: file added after the index was cached", raw_cache)


# --- index.csv and splits
def index_rows(name, rows, bom=False):
    folder = TMP / name
    folder.mkdir()
    for f in ("a.npy", "b.npy"):
        np.save(folder / f, np.full((4, 4), 0.5, np.float32))
    text = "path,target_class,serial,depression_deg,azimuth_deg\n" + "\n".join(rows) + "\n"
    (folder / "index.csv").write_bytes(("\ufeff" if bom else "").encode() + text.encode())
    return f"{len(load_index(folder))} records"


attempt("index.csv duplicate row", lambda: index_rows("dup", ["a.npy,T72,1,17,1", "a.npy,T72,1,17,1"]))
attempt(
    "index.csv one file under two classes",
    lambda: index_rows("two", ["a.npy,T72,1,17,1", "a.npy,BMP2,1,17,1"]),
)
attempt("index.csv with UTF-8 BOM", lambda: index_rows("bom", ["a.npy,T72,1,17,1"], bom=True))


def stray_depression():
    records = [
        ChipRecord(Path(f"/d/{k}.npy"), "A", "s", d, 10.0 * k) for k in range(4) for d in (15.0, 17.0, 15.6)
    ]
    s = split_records(records, "extended")
    return f"train {len(s['train'])} + test {len(s['test'])} of {len(records)}"


attempt("split with chips at 15.6 deg", stray_depression)

# --- pipeline, generate, scaling
from dummies import get_dummy_components  # noqa: E402

from sar_zero123.model.pipeline import SARZero123Pipeline  # noqa: E402

pipe = SARZero123Pipeline(**get_dummy_components())
pipe.set_progress_bar_config(disable=True)
image = torch.rand(1, 1, 32, 32)


def call(**kw):
    args = {
        "d_az": 30.0,
        "d_el": 0.0,
        "num_inference_steps": 2,
        "output_type": "pt",
        "generator": torch.Generator().manual_seed(0),
        **kw,
    }
    out = pipe(image, **args).images
    return f"finite output: {bool(torch.isfinite(out).all())}"


attempt("pipeline d_el=400", lambda: call(d_el=400.0))
attempt("pipeline d_el=1e300", lambda: call(d_el=1e300))
attempt("pipeline d_az=1e300", lambda: call(d_az=1e300))
attempt("pipeline guidance_scale=1e30", lambda: call(guidance_scale=1e30))
attempt("pipeline d_az='30'", lambda: call(d_az="30"))
attempt("pipeline d_az=None", lambda: call(d_az=None))
attempt("pipeline d_az=30+1j", lambda: call(d_az=30 + 1j))
attempt("pipeline guidance_scale='3'", lambda: call(guidance_scale="3"))


def nan_pipe():
    components = get_dummy_components()
    with torch.no_grad():
        next(components["unet"].parameters()).fill_(float("nan"))
    broken = SARZero123Pipeline(**components)
    broken.set_progress_bar_config(disable=True)
    out = broken(image, d_az=30.0, num_inference_steps=1, output_type="pt").images
    return f"finite output: {bool(torch.isfinite(out).all())}"


attempt("pipeline with NaN UNet weights", nan_pipe)
attempt(
    "DecibelScaling.normalize(negative)",
    lambda: f"NaN in output: {bool(np.isnan(DecibelScaling().normalize(np.array([0.5, -0.2]))).any())}",
)

from sar_zero123 import generate  # noqa: E402

pipe.save_pretrained(TMP / "pipe")
np.save(TMP / "big.npy", rng.uniform(0.5, 1.0, (40, 40)).astype(np.float32) * 100)


def gen_big():
    generate.main(
        [
            "--pipeline",
            str(TMP / "pipe"),
            "--image",
            str(TMP / "big.npy"),
            "--d-az",
            "30",
            "--num-inference-steps",
            "1",
            "--output_dir",
            str(TMP / "gen_big"),
        ]
    )
    saturated = np.mean(np.asarray(PIL.Image.open(TMP / "gen_big" / "input.png")) == 255)
    return (
        f"rc 0, wrote {len(list((TMP / 'gen_big').glob('view_*')))} view files, input {saturated:.1%} at 1.0"
    )


attempt("generate: magnitudes 100x the dB range", gen_big)
attempt(
    "generate --out <a file>",
    lambda: generate.main(
        ["--pipeline", str(TMP / "pipe"), "--image", str(TMP / "big.npy"), "--output_dir", str(TMP / "afile")]
    ),
)
attempt(
    "generate --d-el 400",
    lambda: generate.main(
        [
            "--pipeline",
            str(TMP / "pipe"),
            "--image",
            str(TMP / "big.npy"),
            "--d-el",
            "400",
            "--output_dir",
            str(TMP / "g400"),
        ]
    ),
)

# --- metrics, evaluators, simulator, NT-Xent
from sar_zero123.evaluation import metrics  # noqa: E402

x = torch.rand(2, 1, 64, 64)
attempt(
    "ms_ssim betas (0.0448, -0.3, 0.1333)",
    lambda: float(metrics.ms_ssim(x, x * 0.5, betas=(0.0448, -0.3, 0.1333))[0]),
)
attempt("ms_ssim numpy input", lambda: metrics.ms_ssim(x.numpy(), x.numpy()))
attempt("ms_ssim batch 0", lambda: tuple(metrics.ms_ssim(x[:0], x[:0]).shape))
attempt(
    "kuan_filter cu=NaN",
    lambda: f"NaN in output: {bool(metrics.kuan_filter(x, cu=float('nan')).isnan().any())}",
)
attempt(
    "kuan_filter negative image", lambda: "returned a tensor" if metrics.kuan_filter(-x) is not None else None
)
attempt(
    "classification_accuracy float labels",
    lambda: metrics.classification_accuracy(torch.tensor([[0.0, 1.0], [1.0, 0.0]]), torch.tensor([1.7, 0.2])),
)
attempt(
    "azimuth_error_deg (4,1) vs (4,)",
    lambda: tuple(metrics.azimuth_error_deg(torch.zeros(4, 1), torch.zeros(4)).shape),
)
attempt(
    "frechet_distance huge features",
    lambda: metrics.frechet_distance(np.full((4, 2), 1e200) * np.arange(4)[:, None], np.ones((4, 2))),
)

from sar_zero123.evaluation.evaluators import SARClassifier  # noqa: E402

attempt(
    "classifier of one class",
    lambda: (
        SARClassifier(
            SAREncoderConfig(image_size=16, depths=(1,), hidden_sizes=(8,), embedding_size=8), ["T72"]
        )
        and "built"
    ),
)
from sar_zero123.sim import simulate_dataset  # noqa: E402


def sim_dup():
    out = simulate_dataset(
        TMP / "simdup", classes=["TANK", "TANK"], instances=1, azimuth_step_deg=180, size=16
    )
    return f"{len(load_index(out))} chips for 1 class x 2 azimuths x 2 depressions"


attempt("simulate_dataset classes TANK TANK", sim_dup)


def sim_tiny_step():
    from sar_zero123.sim import dataset as simdataset

    if not hasattr(simdataset, "MAX_SIM_CHIPS"):
        return "no bound: would write 1.4e12 chips until the disk fills (not run)"
    simulate_dataset(TMP / "simstep", azimuth_step_deg=1e-9)


attempt("simulate_dataset azimuth_step_deg 1e-9", sim_tiny_step)
from sar_zero123.encoder import nt_xent_loss  # noqa: E402

attempt("nt_xent_loss with 1 pair", lambda: float(nt_xent_loss(torch.randn(1, 4), torch.randn(1, 4))))
json.dump(RESULTS, open(sys.argv[2], "w"), indent=1)
shutil.rmtree(TMP, ignore_errors=True)
