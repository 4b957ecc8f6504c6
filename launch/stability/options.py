"""What a stability run is given (``sygrid bench stability``'s options), shared by the axes' factories."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

from sygrid.fileio import cache_dir_for


@dataclass(frozen=True)
class Options:
    """Paths as given (relative to the working folder, the repository root for the defaults).

    ``models``: the model folder; ``data``: the noise-free test set the binned axes and the depth-noise axis read;
    ``recipe``: the recipe the generated points vary; ``max_images``: images of ``data`` per pass (None: the axis's
    default, 0: all); ``images_per_point``: items generated per (point, seed); ``strategies``: the pose strategies
    measured; ``seeds``: seeds per point (None: each axis's own); ``cache_dir``: generated sets, measurement passes
    and soak logs; ``cell_config``: the simulated cell's file; ``max_cycles``: pick cycles per bin;
    ``cell_perception``: "oracle" or "models"; ``soak_items``, ``soak_minutes``: the soak's generator items and cell
    minutes; ``quick``: each axis's tiny version."""

    models: Path = Path("models/builtin")
    data: Path = Path("datasets/builtin_test")
    recipe: Path = Path("launch/recipes/builtin_test.json")
    max_images: int | None = None
    images_per_point: int = 24  # x 2 seeds: about as many images per point as the depth-noise axis reads
    strategies: tuple[str, ...] = ()
    threads: int = 2
    seeds: int | None = None
    cache_dir: Path = field(default_factory=lambda: cache_dir_for("stability"))
    cell_config: Path = Path("launch/cells/sim.toml")
    max_cycles: int = 6
    cell_perception: str = "oracle"
    soak_items: int = 1000
    soak_minutes: float = 30.0
    quick: bool = False
    progress: bool = False

    def images_or(self, default: int | None, quick: int) -> int | None:
        """Images of ``data`` per pass: ``max_images`` where given (0: all, None), else ``default``; at most
        ``quick`` with ``quick``."""
        n = default if self.max_images is None else (self.max_images or None)
        return min(n or quick, quick) if self.quick else n

    def seeds_or(self, default: tuple[int, ...]) -> tuple[int, ...]:
        """``seeds`` seeds (0 .. n-1) where given, else ``default``."""
        return tuple(range(self.seeds)) if self.seeds is not None else default
