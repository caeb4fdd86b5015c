"""The official training and test scripts on a converted dataset, with no edit.

The official code (cbsropenproject/6dof_face) loads its dataset by name:
`--dataset_mode NAME` imports `data/NAME_dataset.py` and uses its `BaseDataset`
subclass named `NAMEDataset` (case-insensitive). This command adds one such file,
`data/arkittool_dataset.py`, to a checkout of the official code, and prints the flags
that make its `train.py` and `test.py` read a dataset converted by `arkit-tool convert`:

    python -m arkit_tool.official path/to/6dof_face --dataset data/converted
    cd path/to/6dof_face
    python train.py --dataset_mode arkittool --arkittool_dataset /abs/data/converted ...
    python test.py  --dataset_mode arkittool --arkittool_dataset /abs/data/converted ...

What the file's class (`OfficialScriptsDataset` here) does in those scripts:

- The split follows `opt.isTrain`, as the official loader's csv lists do: train.py's
  training set is `--arkittool_train_split` (default `train`) with the official
  augmentation, its validation set and test.py's set are `--arkittool_test_split`
  (default `test`) without it. `--debug` keeps the first 2721 / 1394 samples, as the
  official loader does. The evaluation keys (`tform_inv`, `R_t`, `img_path`, ...) come
  with every sample of the evaluation split.
- `compute_metrics(inference_data)` returns what the official
  `ARKitDataset.compute_metrics` returns (the same keys, numbers and strings),
  computed here: the official one lives in a module that imports its Cython build.
- The augmentation's draws are `ds.item(i, epoch_key)` of `arkit_tool.ARKitFaceDataset`.
  train.py never calls `set_epoch` (the line is commented out), so the key comes from
  what the dataset can see: in a DataLoader worker, the base seed torch draws for the
  workers of each epoch (a new one every epoch, shared by all workers; keys with the top
  bit set); with `--num_threads 0`, the number of training batches served so far divided
  by the batches of one epoch (train.py always runs whole epochs of `len // batch_size`
  batches, drop_last). Every epoch draws afresh, but the draws of a run depend on
  `--num_threads` and, with workers, on torch's random state (train.py does not seed
  it), so two runs differ, as two runs of the official loader do. If `set_epoch` is
  called (uncommenting train.py's line), its epoch is the key: the same batches
  whatever `--num_threads`.
- Nothing imports the official loader (`data/arkit_dataset.py`) or its Cython build.
- A sample that cannot be served is reported on stderr (naming it) and left out of its
  batch; nothing is substituted.

Set ARKIT_TOOL_OFFICIAL_LOG to a file to have every served batch (split, epoch key,
indices) and every `compute_metrics` call (its input and result) appended to it as JSON
lines.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
import tempfile
import warnings
from typing import Any, Dict, List, Optional, Sequence

import numpy as np

NAME = "arkittool"
FILE = f"{NAME}_dataset.py"
# The first line of the file this module writes: how it recognises its own file.
MARKER = "# Written by `python -m arkit_tool.official`"
# The official loader's `nrows` under `--debug` (data/arkit_dataset.py).
DEBUG_ROWS = {True: 2721, False: 1394}
# Epoch keys drawn from a DataLoader's worker seed carry this bit, so they never equal a
# counted epoch (0, 1, 2, ...) or one given by set_epoch.
SEED_KEY_BIT = 1 << 63
LOG_ENV = "ARKIT_TOOL_OFFICIAL_LOG"

LOSSES = ["loss_total", "loss_corr", "loss_recon3d", "loss_uv", "loss_mat", "loss_seg"]
# (official key, inference_data key, scale to mm or None, format) of the evaluation
# metrics, in the official dict's order; each is the mean over the evaluated samples.
MEANS = [
    ("3DRecon", "3DRecon", 1000.0, "%.2f mm"),
    ("ADD", "ADD", 1000.0, "%.2f mm"),
    ("pitch_mae", "pitch_mae", None, "%.2f \u00b0"),
    ("yaw_mae", "yaw_mae", None, "%.2f \u00b0"),
    ("roll_mae", "roll_mae", None, "%.2f \u00b0"),
    ("tx_mae", "tx_mae", 1000.0, "%.2f mm"),
    ("ty_mae", "ty_mae", 1000.0, "%.2f mm"),
    ("tz_mae", "tz_mae", 1000.0, "%.2f mm"),
]


def _log(record: Dict[str, Any]) -> None:
    path = os.environ.get(LOG_ENV)
    if not path:
        return
    line = json.dumps(record, default=_jsonable) + "\n"
    with open(path, "a", encoding="utf-8") as f:
        f.write(line)


def _jsonable(x: Any) -> Any:
    if isinstance(x, np.generic):
        return x.item()
    if isinstance(x, np.ndarray):
        return x.tolist()
    raise TypeError(f"{type(x).__name__} is not JSON serializable")


def compute_metrics(inference_data: Dict[str, Any], evaluation: bool) -> Dict[str, Any]:
    """The official `ARKitDataset.compute_metrics` of `inference_data` (what the
    official model's `inference_curr_batch` collects): the six losses averaged over the
    samples (each batch's loss weighted by its size) and, when `evaluation` (test.py:
    the options have `eval`), the pose metrics as the official strings: `pnp_fail` (a
    count), `3DRecon` and `ADD` (mean, mm), `pitch_mae`, `yaw_mae`, `roll_mae` (mean,
    degrees), `tx_mae`, `ty_mae`, `tz_mae` (mean, mm), `5°5cm` (percent of samples
    within 5 degrees and 5 cm), `5°10cm` (percent within 10 degrees and 5 cm: the
    official key, whose name says 10 cm) and `mean_IoU` (mean relative scale error).

    Differs from the official function only when nothing was evaluated (no batch: the
    split is smaller than the batch size, and the official DataLoader drops the
    incomplete batch): the values are NaN with a warning, where the official function
    gives NaN losses and raises ZeroDivisionError for the success rates."""
    sizes = np.asarray(inference_data["batch_size"], dtype=np.int64)
    if sizes.size == 0:
        warnings.warn(
            "arkittool: compute_metrics: no batch was evaluated (the split has fewer samples "
            "than the batch size, and the official DataLoader drops an incomplete batch); "
            "the metrics are NaN",
            RuntimeWarning,
            stacklevel=2,
        )
    out: Dict[str, Any] = {}
    with np.errstate(invalid="ignore", divide="ignore"):
        for name in LOSSES:
            # Each batch's mean loss times its size, over the samples.
            out[name] = (np.asarray(inference_data[name]) * sizes).sum() / sizes.sum()
    if not evaluation:
        return out
    out["pnp_fail"] = inference_data["pnp_fail"]
    for key, source, scale, fmt in MEANS:
        # The values' own dtype (3DRecon is float32 in the official model) is kept: the
        # mean is taken, and scaled, in it, as np.mean does in the official function.
        values = np.asarray(inference_data[source])
        mean = values.mean() if values.size else math.nan
        out[key] = fmt % (mean if scale is None else mean * scale)
    count = inference_data["total_count"]
    strict = inference_data["strict_success"] / count if count else math.nan
    easy = inference_data["easy_success"] / count if count else math.nan
    iou = np.asarray(inference_data["IoU"])
    out["5\u00b05cm"] = "%.2f " % (strict * 100)
    out["5\u00b010cm"] = "%.2f" % (easy * 100)
    out["mean_IoU"] = "%.4f" % (iou.mean() if iou.size else math.nan)
    return out


def _served_per_epoch(n: int, batch_size: int, max_dataset_size: Any) -> int:
    """Training samples the official `CustomDatasetDataLoader` takes in one epoch with
    no worker processes: whole batches (drop_last), and its loop stops after the batch
    `i` with `i * batch_size >= max_dataset_size` (that batch is fetched)."""
    batches = n // batch_size
    try:
        limit = float(max_dataset_size)
    except (TypeError, ValueError):
        limit = math.inf
    if math.isfinite(limit):
        batches = min(batches, max(0, math.ceil(limit / batch_size)) + 1)
    return batches * batch_size


class OfficialScriptsDataset:
    """A converted dataset as the official code's `--dataset_mode` expects it (the
    mixin of the class `data/arkittool_dataset.py` defines; see this module's doc).

    Built from the official options `opt`: `isTrain` picks the split and the mode,
    `img_size`, `n_pts`, `batch_size`, `max_dataset_size` and `debug` are the official
    ones, `hasattr(opt, 'eval')` (test.py) turns on the pose metrics, and the
    `--arkittool_*` options (added by `modify_commandline_options`) name the dataset.
    `BaseDataset.__init__` is not called: it reads `opt.dataroot`, which the official
    options do not define. Only plain values are kept from `opt` (train.py later
    attaches its visualizer to it)."""

    def __init__(self, opt: Any) -> None:
        import arkit_tool

        path = getattr(opt, "arkittool_dataset", None)
        if not path:
            raise SystemExit(
                "arkittool: pass --arkittool_dataset DIR (the folder `arkit-tool convert` wrote); "
                "`python -m arkit_tool.official OFFICIAL_DIR --dataset DIR` prints the flags"
            )
        self.is_train = bool(opt.isTrain)
        self.evaluation = hasattr(opt, "eval")
        split = opt.arkittool_train_split if self.is_train else opt.arkittool_test_split
        store = getattr(opt, "arkittool_crop_store", "auto")
        try:
            self.ds = arkit_tool.ARKitFaceDataset(
                path,
                split=split,
                mode="train" if self.is_train else "eval",
                compat=opt.arkittool_compat,
                img_size=opt.img_size,
                n_pts=opt.n_pts,
                seed=opt.arkittool_seed,
                resources=getattr(opt, "arkittool_resources", None),
                corr="dense",
                crop_store=None if store == "none" else store,
            )
        except arkit_tool.DataError as error:
            raise SystemExit(f"arkittool: {error}") from None
        n = len(self.ds)
        if n == 0:
            raise SystemExit(f"arkittool: {path}: the split {split!r} has no samples (--arkittool_"
                             f"{'train' if self.is_train else 'test'}_split)")
        self.size = min(n, DEBUG_ROWS[self.is_train]) if getattr(opt, "debug", False) else n
        self.split = split
        # set by the official CustomDatasetDataLoader.set_epoch (never called by train.py)
        self.current_epoch: Optional[int] = None
        self._served = 0
        self._per_epoch = max(1, _served_per_epoch(self.size, int(opt.batch_size), opt.max_dataset_size))
        print(
            f"arkittool: {path}: split {split!r}, {self.size} samples, "
            f"{'training (augmented)' if self.is_train else 'evaluation'}, compat {opt.arkittool_compat!r}, "
            f"crops from {'the store ' + self.ds.crop_store if self.ds.crop_store else 'the JPEGs'}",
            file=sys.stderr,
        )

    @staticmethod
    def modify_commandline_options(parser: Any, is_train: bool) -> Any:
        g = parser.add_argument_group("arkittool (a dataset converted by arkit-tool)")
        g.add_argument("--arkittool_dataset", default=None, metavar="DIR",
                       help="the folder `arkit-tool convert` wrote (holding dataset.json)")
        g.add_argument("--arkittool_compat", default="official", choices=["official", "exact"],
                       help="the official loader's rules for box, crop, mask, points and UV map, "
                            "or arkit-tool's own (docs/python.md)")
        g.add_argument("--arkittool_train_split", default="train",
                       help="the split train.py trains on (opt.isTrain)")
        g.add_argument("--arkittool_test_split", default="test",
                       help="the split of train.py's validation and of test.py")
        g.add_argument("--arkittool_seed", type=int, default=0,
                       help="the augmentation's seed (draws from seed, epoch key, index)")
        g.add_argument("--arkittool_resources", default=None, metavar="DIR",
                       help="the release's resource folder, if it moved since `convert`")
        g.add_argument("--arkittool_crop_store", default="auto", metavar="DIR",
                       help="'auto': the store `arkit-tool crops` wrote for this compat and "
                            "img_size when there; 'none': decode the JPEGs; or a store folder")
        return parser

    def __len__(self) -> int:
        return self.size

    def _epoch_key(self, n: int) -> int:
        if self.current_epoch is not None:
            return int(self.current_epoch)
        import torch.utils.data

        info = torch.utils.data.get_worker_info()
        if info is not None:
            # Every worker of an epoch has seed = base_seed + id; a new base each epoch.
            return ((int(info.seed) - int(info.id)) % SEED_KEY_BIT) | SEED_KEY_BIT
        key = self._served // self._per_epoch
        self._served += n
        return key

    def _check(self, indices: Sequence[int]) -> List[int]:
        out = []
        for i in indices:
            i = int(i)
            if not 0 <= i < self.size:
                raise IndexError(f"arkittool: index {i} out of range for {self.size} samples")
            out.append(i)
        return out

    def __getitems__(self, indices: Sequence[int]) -> List[Any]:
        import arkit_tool

        idx = self._check(indices)
        key = self._epoch_key(len(idx)) if self.is_train else 0
        self.ds.set_epoch(key)
        _log({"pid": os.getpid(), "split": self.split, "train": self.is_train, "epoch": key, "indices": idx})
        try:
            return self.ds.__getitems__(idx)
        except arkit_tool.DataError:
            pass
        # One sample failed: serve the others, report each that fails.
        items: List[Any] = []
        for i in idx:
            try:
                items.append(self.ds.item(i))
            except arkit_tool.DataError as error:
                k = self.ds.key(i)
                print(f"arkittool: skipped sample {i} ({'/'.join(k[:3])}) of split {self.split!r}: {error}",
                      file=sys.stderr)
        if not items:
            raise arkit_tool.DataError(f"arkittool: no sample of the batch {idx} could be served (see above)")
        return items

    def __getitem__(self, index: int) -> Any:
        return self.__getitems__([index])[0]

    def compute_metrics(self, inference_data: Dict[str, Any]) -> Dict[str, Any]:
        """The official `compute_metrics` (see `arkit_tool.official.compute_metrics`)."""
        metrics = compute_metrics(inference_data, self.evaluation)
        _log({"compute_metrics": {"evaluation": self.evaluation, "inference_data": inference_data,
                                  "metrics": metrics}})
        return metrics


def _generated_file() -> str:
    from arkit_tool import __version__

    return f'''{MARKER} (arkit_tool {__version__}).
# It lets this code's train.py and test.py read a dataset converted by arkit-tool:
#     python train.py --dataset_mode {NAME} --arkittool_dataset DIR [...]
# data/__init__.py imports data/<dataset_mode>_dataset.py and uses its BaseDataset
# subclass named <dataset_mode>Dataset; everything else is in the arkit_tool package
# (arkit_tool/official.py). Delete this file to remove it; run the command again after
# upgrading arkit_tool.
from data.base_dataset import BaseDataset

try:
    from arkit_tool.official import OfficialScriptsDataset
except ImportError as error:
    raise ImportError(
        "data/{FILE} needs the arkit_tool package in this Python "
        "(pip install ./python in the arkit-tool repository): %s" % error
    ) from error


class ArkittoolDataset(OfficialScriptsDataset, BaseDataset):
    """A dataset converted by arkit-tool (see arkit_tool.official); BaseDataset.__init__
    is not called (it reads opt.dataroot, which these options do not define)."""
'''


def write_dataset_file(official_dir: str, force: bool = False) -> str:
    """Writes `data/arkittool_dataset.py` into the official checkout `official_dir`
    (atomically: a temporary file renamed into place). Refuses a folder that is not the
    official code and an existing file of that name not written by this module (unless
    `force`). Returns the file's path."""
    data_dir = os.path.join(official_dir, "data")
    init = os.path.join(data_dir, "__init__.py")
    if not os.path.isfile(init) or not os.path.isfile(os.path.join(data_dir, "base_dataset.py")):
        raise SystemExit(f"{official_dir}: not a checkout of the official code (no data/__init__.py "
                         "and data/base_dataset.py); clone https://github.com/cbsropenproject/6dof_face")
    with open(init, encoding="utf-8", errors="replace") as f:
        text = f.read()
    if "find_dataset_using_name" not in text or '"_dataset"' not in text:
        raise SystemExit(f"{init}: does not load datasets by name (find_dataset_using_name, "
                         "data/<name>_dataset.py); is this the official code?")
    target = os.path.join(data_dir, FILE)
    if os.path.exists(target) and not force:
        with open(target, encoding="utf-8", errors="replace") as f:
            first = f.readline()
        if not first.startswith(MARKER):
            raise SystemExit(f"{target}: exists and was not written by this command; "
                             "pass --force to replace it")
    fd, tmp = tempfile.mkstemp(prefix=f".{FILE}.", dir=data_dir)
    try:
        with os.fdopen(fd, "w", encoding="utf-8") as f:
            f.write(_generated_file())
        os.chmod(tmp, 0o644)
        os.replace(tmp, target)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise
    return target


def _absolute(dataset: str) -> str:
    """`dataset` as the official scripts are given it: a bucket URL as it is, a folder
    made absolute (the scripts run in the official checkout)."""
    from ._storage import is_url

    return dataset if is_url(dataset) else os.path.abspath(dataset)


def flags(dataset: str, compat: str = "official", train_split: str = "train",
          test_split: str = "test", seed: int = 0) -> List[str]:
    """The official scripts' flags that select the converted dataset `dataset`."""
    out = ["--dataset_mode", NAME, "--arkittool_dataset", _absolute(dataset)]
    if compat != "official":
        out += ["--arkittool_compat", compat]
    if train_split != "train":
        out += ["--arkittool_train_split", train_split]
    if test_split != "test":
        out += ["--arkittool_test_split", test_split]
    if seed != 0:
        out += ["--arkittool_seed", str(seed)]
    return out


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="python -m arkit_tool.official",
        formatter_class=argparse.RawDescriptionHelpFormatter,
        description="""\
Lets the official PerspNet code (github.com/cbsropenproject/6dof_face) train and test on a
dataset converted by `arkit-tool convert`, with its train.py and test.py unchanged.

It writes one file, OFFICIAL_DIR/data/arkittool_dataset.py (the official data/__init__.py
loads `--dataset_mode NAME` from data/NAME_dataset.py), checks the dataset, and prints the
flags to pass. In the official code's Python environment (its requirements and this
package installed):

  python -m arkit_tool.official ~/6dof_face --dataset data/converted
  arkit-tool crops --dataset data/converted --compat official    # optional: crops stored once
  D=$PWD/data/converted
  cd ~/6dof_face
  python train.py --dataset_mode arkittool --arkittool_dataset $D --name run1
  python test.py  --dataset_mode arkittool --arkittool_dataset $D --name run1 --batch_size 16

Its dataset options (see `python train.py --dataset_mode arkittool --help`):
--arkittool_dataset DIR, --arkittool_compat official|exact, --arkittool_train_split,
--arkittool_test_split, --arkittool_seed, --arkittool_resources, --arkittool_crop_store.

train.py trains on the train split (augmented) and validates on the test split; test.py
evaluates the test split with the official metrics. Epochs draw fresh augmentation
without set_epoch (from the DataLoader's per-epoch worker seed, or by counting batches
with --num_threads 0), so the draws depend on --num_threads. Nothing imports the
official loader's Cython build. test.py's default batch of 64 drops an incomplete
batch: on a small test split pass a smaller --batch_size. train.py validates with a batch
of 64 whatever the flags, so a test split under 64 samples gives NaN validation losses.
See docs/python.md, "The official scripts".""",
    )
    p.add_argument("official_dir", metavar="OFFICIAL_DIR",
                   help="a checkout of the official code (holding train.py and data/)")
    p.add_argument("--dataset", required=True, metavar="DIR",
                   help="the converted dataset (the folder holding dataset.json), or the URL "
                        "it was published to with `arkit-tool push` (s3://bucket/prefix)")
    p.add_argument("--compat", default="official", choices=["official", "exact"],
                   help="the official loader's rules (default) or arkit-tool's own")
    p.add_argument("--train-split", default="train", help="the split train.py trains on (default train)")
    p.add_argument("--test-split", default="test",
                   help="the split train.py validates on and test.py evaluates (default test)")
    p.add_argument("--seed", type=int, default=0, help="the augmentation's seed (default 0)")
    p.add_argument("--force", action="store_true",
                   help="replace a data/arkittool_dataset.py not written by this command")
    return p


def main(argv: Optional[Sequence[str]] = None) -> int:
    a = _parser().parse_args(argv)
    import arkit_tool

    try:
        data = arkit_tool.open_dataset(a.dataset)
    except arkit_tool.DataError as error:
        raise SystemExit(f"--dataset: {error}") from None
    splits = data.splits
    for flag, split in (("--train-split", a.train_split), ("--test-split", a.test_split)):
        if not splits.get(split):
            raise SystemExit(f"{flag}: {a.dataset} has no samples in split {split!r} (splits: {splits})")
    verts = len(data.sample(0)["verts"])
    if verts != 1220:
        raise SystemExit(f"--dataset: {a.dataset}: meshes of {verts} vertices; the official network "
                         "predicts the 1,220 vertices of the ARKit face (convert with --resources)")
    target = write_dataset_file(a.official_dir, a.force)
    f = flags(a.dataset, a.compat, a.train_split, a.test_split, a.seed)
    from ._storage import is_url

    where = _absolute(a.dataset)
    print(f"wrote {target}")
    print(f"dataset: {where}: {splits}")
    store = os.path.join(where, "crops", f"{a.compat}-192")
    if not is_url(a.dataset) and not os.path.isfile(os.path.join(store, "crops.json")):
        print(f"no crop store at {store}: every epoch decodes the JPEGs; to store the crops once:\n"
              f"  arkit-tool crops --dataset {where} --compat {a.compat}")
    print("flags for the official train.py and test.py:")
    print("  " + " ".join(f))
    print("for example, in the official code's folder:")
    print(f"  python train.py {' '.join(f)} --name arkittool_run")
    print(f"  python test.py {' '.join(f)} --name arkittool_run --batch_size 16")
    return 0


if __name__ == "__main__":
    sys.exit(main())
