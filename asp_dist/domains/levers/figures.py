"""The lever game's figure, from its rows' figure_data (Domain.draw_figures): the first two principal components
of the CommNet's communication vectors (last f-block) of a fixed set of games, coloured by agent ID, for the
base and the new agents."""

from __future__ import annotations

from pathlib import Path

from asp_dist.analysis.plots import Figure, scatter_figures


def draw(payloads: list[tuple[dict, dict]], out_dir: Path) -> tuple[list[Figure], list[str]]:
    return scatter_figures(payloads, out_dir, kind="comm", color_key="ids", color_label="agent ID", pca=True,
                           what="PCA (first two components) of communication vectors coloured by agent ID")
