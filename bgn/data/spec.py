"""What identifies a dataset file: scene, its parameters, sizes, seed, fps and split.

The cache key is a hash of everything that changes the generated numbers, so a different
parameter set never reuses a stale file.
"""

from __future__ import annotations

import hashlib
import json
from dataclasses import asdict, dataclass, field, fields, is_dataclass
from pathlib import Path
from typing import Any

from bgn.coerce import as_int, need_float, need_int
from bgn.sim import SCENES, Scene, make_scene

SPLITS = ("train", "val", "test")
# Dataset config keys that do not change the generated numbers (they configure loading).
LOADER_KEYS = frozenset({"history", "batch_size", "num_workers", "train_sims", "val_samples",
                         "test_samples",
                         "in_memory", "generate_workers", "unroll"})
SIZE_KEYS = ("n_sims", "n_frames", "seed")
IMPORTED = "imported"  # the scene of imported data (bgn.sim.imported, bgn.data.importing)


def check_fps(value: Any) -> float:
    """``fps`` as a float > 0: the one home of the rule (the spec, and the config checks of
    ``bgn.training.validate`` before any spec is built)."""
    return need_float(value, "fps", 0.0, why=" (frames per unit of simulated time)")


@dataclass
class LoaderOptions:
    """How a dataset node says its frames are loaded (``LOADER_KEYS`` but the generation's
    ``generate_workers``): the one home of their defaults (the config schema
    ``bgn.training.config.LoaderNode`` is this class) and of their rules (``from_config``, which
    the DataModule and ``bgn.training.validate`` both call)."""

    history: int = 5                  # k previous velocities in the input window (>= 0)
    unroll: int = 0                   # training steps unrolled on the model's own frames
    batch_size: int = 64
    val_samples: int | None = None  # validation frames spread over all val sims (null: all)
    test_samples: int | None = None  # test frames spread over all test sims (null: all)
    num_workers: int = 0
    train_sims: int | None = None  # train on the first n simulations only (null: all)
    in_memory: bool = True

    @classmethod
    def from_config(cls, dataset: Any, n_sims: int, sims_why: str | None = None,
                    ) -> LoaderOptions:
        """The loader keys of a ``dataset`` node (defaults where it names none), checked: a
        bad value raises ``ConfigError`` (a ``ValueError``) naming it. ``n_sims``: the train
        split's simulations, the most ``train_sims`` may keep (``sims_why`` says so)."""
        d = cls()

        def get(key: str) -> Any:
            node = dataset.get if hasattr(dataset, "get") else (lambda k, default=None: default)
            return node(key, getattr(d, key))

        history = need_int(get("history"), "dataset.history", 0)
        unroll = need_int(get("unroll"), "dataset.unroll", 0,
                          why=": training steps unrolled on the model's own frames")
        batch_size = need_int(get("batch_size"), "dataset.batch_size", 1)
        num_workers = need_int(get("num_workers"), "dataset.num_workers", 0)
        val_samples = need_int(get("val_samples"), "dataset.val_samples", 1, optional=True,
                               why=": validation frames (null: the whole validation split)")
        test_samples = need_int(get("test_samples"), "dataset.test_samples", 1, optional=True,
                                why=": test frames (null: the whole test split)")
        train_sims = need_int(get("train_sims"), "dataset.train_sims", 1, n_sims, optional=True,
                              why=sims_why or f" (at most dataset.n_sims={n_sims})")
        assert history is not None and unroll is not None  # not optional: never None
        assert batch_size is not None and num_workers is not None
        return cls(history, unroll, batch_size, val_samples, test_samples, num_workers,
                   train_sims, bool(get("in_memory")))


def imported_dir(data_dir: str | Path, name: str) -> Path:
    """Where an import named ``name`` keeps its three files."""
    return Path(data_dir) / IMPORTED / name


def data_dir_problem(data_dir: str | Path) -> str | None:
    """Why ``data_dir`` cannot hold dataset folders (it, or a folder above it, is a file), or
    None; the commands refuse such a ``paths.data_dir`` before any work."""
    path = Path(data_dir)
    for q in (path, *path.parents):
        if q.exists():
            if q.is_dir():
                return None
            what = "is a file" if q == path else f"lies under the file {q}"
            return (f"paths.data_dir={data_dir} {what}, not a folder; give the folder that "
                    "holds (or is to hold) the datasets")
    return None


def _plain(value: Any) -> Any:
    """Config values (OmegaConf containers, dataclasses, tuples) -> JSON-able builtins."""
    if is_dataclass(value) and not isinstance(value, type):
        return _plain(asdict(value))
    if isinstance(value, dict) or hasattr(value, "items"):
        return {str(k): _plain(v) for k, v in value.items()}
    if isinstance(value, list | tuple) or (hasattr(value, "__iter__")
                                           and not isinstance(value, str | bytes)):
        return [_plain(v) for v in value]
    return value


@dataclass(frozen=True)
class DatasetSpec:
    """Everything that determines the arrays of one split's file."""

    scene: str
    n_sims: int
    n_frames: int
    seed: int
    fps: float
    split: str
    params: dict = field(default_factory=dict)  # scene parameters (config values)
    # imported data (scene "imported"): (n_sims, n_frames) of train, val and test, read from
    # the files (each split has its own); empty for generated data
    sizes: tuple[tuple[int, int], ...] = ()

    def __post_init__(self) -> None:
        if self.scene not in SCENES:
            raise ValueError(f"dataset.scene={self.scene!r} is unknown; choose one of "
                             f"{sorted(SCENES)}")
        if self.split not in SPLITS:
            raise ValueError(f"split={self.split!r}; choose one of {SPLITS}")
        check_fps(self.fps)
        as_int(self.n_sims, "dataset.n_sims", 1)
        as_int(self.n_frames, "dataset.n_frames", 3)

    @classmethod
    def from_config(cls, dataset: Any, fps: float, split: str,
                    data_dir: str | Path | None = None) -> DatasetSpec:
        """Build from a ``dataset`` config node (``scene`` + scene parameters + sizes). An
        imported dataset (``scene: imported``, ``name``) is read from its files under
        ``data_dir`` instead (``fps`` is then the files')."""
        cfg = _plain(dataset)
        if cfg.get("scene") == IMPORTED:
            return cls.imported(str(cfg.get("name")), "data" if data_dir is None else data_dir,
                                split)
        missing = [k for k in ("scene", *SIZE_KEYS) if k not in cfg]
        if missing:
            raise ValueError(f"dataset config lacks {missing}; see conf/dataset/*.yaml")
        params = {k: v for k, v in cfg.items()
                  if k not in LOADER_KEYS and k not in SIZE_KEYS and k != "scene"}
        spec = cls(scene=cfg["scene"], n_sims=int(cfg["n_sims"]), n_frames=int(cfg["n_frames"]),
                   seed=int(cfg["seed"]), fps=float(fps), split=split, params=params)
        spec.build_scene()  # fail now, with the scene's own message, on a bad parameter
        return spec

    @classmethod
    def imported(cls, name: str, data_dir: str | Path, split: str = "train") -> DatasetSpec:
        """The spec of an import's files ``<data_dir>/imported/<name>/<split>.h5``: scene
        parameters, frame rate and each split's sizes from the files' attributes."""
        import h5py

        directory = imported_dir(data_dir, name)
        sizes, config, fps = [], {}, 0.0
        for part in SPLITS:
            path = directory / f"{part}.h5"
            if not path.is_file():
                known = sorted(p.name for p in directory.parent.glob("*") if p.is_dir()) \
                    if directory.parent.is_dir() else []
                raise ValueError(
                    f"no imported dataset {name!r}: {path} does not exist (imported under "
                    f"{directory.parent}: {', '.join(known) or 'none'}); import it first with "
                    f"`python -m bgn.data.import <path> name={name} paths.data_dir={data_dir}`")
            try:
                with h5py.File(path, "r") as f:
                    sizes.append((int(f.attrs["n_sims"]), int(f.attrs["n_frames"])))
                    if part == "train":
                        config, fps = json.loads(f.attrs["config"]), float(f.attrs["fps"])
            except (OSError, KeyError, ValueError) as err:  # a damaged file: exit 1, not 2
                from bgn.data.raw import DataImportError

                raise DataImportError(f"imported dataset {name!r}: {path} cannot be read ({err}); "
                                 f"import it again with `python -m bgn.data.import <path> "
                                 f"name={name} overwrite=true`") from None
        n_sims, n_frames = sizes[SPLITS.index(split)]
        return cls(IMPORTED, n_sims, n_frames, 0, fps, split, config["params"], tuple(sizes))

    def build_scene(self) -> Scene:
        return make_scene(self.scene, **self.params)

    @property
    def dt(self) -> float:
        return 1.0 / self.fps

    def generating_config(self) -> dict:
        """The full parameter set of the scene (defaults filled in), sizes and seed."""
        scene = self.build_scene()
        fixed = SCENES[self.scene][1]  # set by the scene's name, not by config
        resolved = {f.name: _plain(getattr(scene, f.name))
                    for f in fields(scene) if f.name not in fixed}  # type: ignore[arg-type]
        return {"scene": self.scene, "params": resolved, "n_sims": self.n_sims,
                "n_frames": self.n_frames, "seed": self.seed}

    def key(self) -> str:
        """Short hash of the generating config (fps and split are spelled out in the name)."""
        blob = json.dumps(self.generating_config(), sort_keys=True).encode()
        return hashlib.sha256(blob).hexdigest()[:10]

    def filename(self) -> str:
        if self.scene == IMPORTED:  # found by name, never generated: no cache key
            return f"{IMPORTED}/{self.params['name']}/{self.split}.h5"
        return f"{self.scene}_{self.key()}_fps{self.fps:g}_{self.split}.h5"

    def path(self, data_dir: str | Path) -> Path:
        return Path(data_dir) / self.filename()

    def with_split(self, split: str) -> DatasetSpec:
        n_sims, n_frames = (self.sizes[SPLITS.index(split)] if self.sizes
                            else (self.n_sims, self.n_frames))
        return DatasetSpec(self.scene, n_sims, n_frames, self.seed, self.fps, split,
                           self.params, self.sizes)

    def regenerate_hint(self, data_dir: str | Path | None = None) -> str:
        """The command that writes this spec's files: the scene, fps, sizes, seed, every
        parameter that differs from the scene's default, and the data directory. Imported
        data: the import's command."""
        if self.scene == IMPORTED:
            if not self.params.get("source"):  # imported from memory
                return f"bgn.data.from_arrays(..., name={self.params['name']!r}, overwrite=True)"
            where = [] if data_dir is None else [
                _shell(f"paths.data_dir={Path(data_dir).parent.parent}")]
            return " ".join(["python -m bgn.data.import",
                             _shell(str(self.params["source"])),
                             _shell(f"name={self.params['name']}"), "overwrite=true", *where])
        cls, fixed = SCENES[self.scene]
        defaults = {f.name: _plain(f.default) for f in fields(cls) if f.name not in fixed}
        resolved = self.generating_config()["params"]
        parts = [f"dataset={self.scene}", f"fps={self.fps:g}", f"dataset.n_sims={self.n_sims}",
                 f"dataset.n_frames={self.n_frames}", f"dataset.seed={self.seed}"]
        parts += [_shell(f"dataset.{k}={_override(v)}") for k, v in resolved.items()
                  if k in defaults and v != defaults[k]]
        if data_dir is not None:
            parts.append(_shell(f"paths.data_dir={data_dir}"))
        return "python -m bgn.train.generate " + " ".join(parts)


def _override(value: Any) -> str:
    """A config value in Hydra's override syntax (lists and dicts included)."""
    if isinstance(value, dict):
        return "{" + ",".join(f"{k}:{_override(v)}" for k, v in value.items()) + "}"
    if isinstance(value, list | tuple):
        return "[" + ",".join(_override(v) for v in value) + "]"
    if isinstance(value, bool):
        return str(value).lower()
    return repr(value) if isinstance(value, float) else str(value)


def _shell(arg: str) -> str:
    """``arg`` quoted for a POSIX shell when it needs it."""
    import shlex

    return shlex.quote(arg)
