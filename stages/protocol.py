"""What a pipeline stage is: a module with a format version, its upstream stages, the dataset inputs it reads and a
`run` function that reads upstream artifacts through the workspace and writes its own through a writer bound to
its transaction."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Protocol

from fullview.io.dataset import Dataset
from fullview.io.workspace import StageWriter, Workspace


@dataclass(frozen=True, kw_only=True)
class StageContext:
    options: Any  # the stage's options dataclass (fullview.sfm.options)
    dataset: Dataset  # the input images, hand points, ground truth
    ws: Workspace  # read access to the upstream stages' artifacts
    out: StageWriter  # the only way to write this stage's artifacts


class Stage(Protocol):
    VERSION: int  # format version of the stage's artifacts (bump to invalidate old ones)
    UPSTREAM: tuple[str, ...]  # stages whose artifacts it reads
    INPUTS: tuple[str, ...]  # dataset inputs it reads: "images", "hand_points"

    def run(self, ctx: StageContext) -> dict:  # returns a JSON-able summary for the manifest
        ...
