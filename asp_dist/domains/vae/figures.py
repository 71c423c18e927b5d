"""The VAE's figures, from its rows' figure_data (Domain.draw_figures; asp_dist.analysis.plots draws the rest):
the 2-D latent codes of the base and new encoders coloured by digit (cells with vae_latent_dim = 2), and the
reconstructions of one test image per digit through every encoder→decoder pairing."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from asp_dist.analysis.plots import (MAX_FIGURES_PER_KIND, Figure, pick_rows, plt, safe_name, save_figure,
                                     scatter_figures)  # plt: with the Agg backend the analysis sets


def draw(payloads: list[tuple[dict, dict]], out_dir: Path) -> tuple[list[Figure], list[str]]:
    latents, notes = scatter_figures(payloads, out_dir, kind="latent2d", color_key="labels", color_label="digit",
                                     what="2-D latent codes coloured by digit")
    recon, more = reconstructions(payloads, out_dir)
    return latents + recon, notes + more


def reconstructions(payloads: list[tuple[dict, dict]], out_dir: Path) -> tuple[list[Figure], list[str]]:
    """VAE reconstructions of one test image per digit: original, base, and the two mixed pairings."""
    figures, notes = [], []
    by_key: dict[tuple, list[tuple[dict, dict]]] = {}
    for rec, data in payloads:
        if isinstance(data.get("recon"), dict):
            by_key.setdefault((rec["domain"], rec["condition"]), []).append((rec, data["recon"]))
    for (domain, cond), items in sorted(by_key.items())[:MAX_FIGURES_PER_KIND]:
        try:
            trial, chosen = pick_rows(items, 3)
            first = chosen[0][1]
            side = int(first.get("side", 28))
            lines = [("original", first["original"]), ("base → base", first["base"])]
            for rec, r in chosen:
                tag = f"{rec['treatment'].upper()}+{rec['paired']}"
                lines.append((f"{tag}: base enc → new dec", r["base_encoder_new_decoder"]))
                lines.append((f"{tag}: new enc → base dec", r["new_encoder_base_decoder"]))
            cols = len(first["original"])
            # One mosaic image (rows of digits) instead of one axes per digit: far cheaper to draw and save.
            mosaic = np.vstack([np.hstack([np.asarray(images[j], dtype=float).reshape(side, side) for j in range(cols)])
                                for _, images in lines])
            fig, ax = plt.subplots(figsize=(0.75 * cols + 2.2, 0.75 * len(lines) + 0.6), layout="constrained")
            ax.imshow(mosaic, cmap="gray", vmin=0, vmax=255)
            ax.set_yticks([side * (i + 0.5) for i in range(len(lines))])
            ax.set_yticklabels([name for name, _ in lines], fontsize=7)
            ax.set_xticks([side * (j + 0.5) for j in range(cols)])
            ax.set_xticklabels([str(v) for v in first.get("labels", range(cols))], fontsize=8)
            ax.xaxis.tick_top()
            for k in range(1, len(lines)):
                ax.axhline(k * side - 0.5, color="white", linewidth=1)
        except (KeyError, ValueError, TypeError, IndexError) as err:
            plt.close("all")
            notes.append(f"reconstructions of {domain} ({cond}) not drawn: {err}")
            continue
        fig.suptitle(f"{domain}, trial {trial}" + (f", {cond}" if cond != "all" else "")
                     + ": reconstructions of one test image per digit", fontsize=10)
        stem = safe_name(f"{domain}_reconstructions_{cond}")
        figures.append(Figure(stem, f"{domain}: reconstructions" + (f" ({cond})" if cond != "all" else ""),
                              "Rows: original test image, the base VAE, and for ASP at a few paired counts the two "
                              "mixed pairings the metric scores.", save_figure(fig, out_dir, stem)))
    return figures, notes


