"""PNG figures like the paper's (matplotlib, Agg), each written atomically."""

from __future__ import annotations

import os

import numpy as np

from identified.dataset import atomic_write

__all__ = ["curves_figure", "save", "series_figure"]


def _plt():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def save(fig, path: str) -> str:
    """Write ``fig`` to ``path`` atomically and close it; returns the path."""
    atomic_write(path, lambda fh: fig.savefig(fh, format="png", dpi=110), binary=True)
    _plt().close(fig)
    return path


def curves_figure(path: str, title: str, curves: dict[str, dict[str, np.ndarray]]) -> str:
    """Position and quaternion error against the time step, one line per method (log scale)."""
    plt = _plt()
    fig, axes = plt.subplots(1, 2, figsize=(11, 3.8), constrained_layout=True)
    for label, c in curves.items():
        for ax, key in zip(axes, ("pos", "quat")):
            y = np.asarray(c[key], dtype=float)
            y = np.where(np.isfinite(y), np.maximum(y, 1e-17), np.nan)
            ax.semilogy(np.arange(y.size), y, label=label)
    for ax, lab in zip(axes, ("position error (m)", "quaternion error")):
        ax.set_xlabel("time step")
        ax.set_ylabel(lab)
        ax.grid(True, which="both", alpha=0.3)
    axes[1].legend(fontsize=8)
    fig.suptitle(title)
    return save(fig, path)


def series_figure(path: str, title: str, series: dict[str, tuple[np.ndarray, np.ndarray]], xlabel: str,
                  ylabel: str, logx: bool = False) -> str:
    """One line per label from ``(x, y)`` pairs, log y (and optionally log x)."""
    plt = _plt()
    fig, ax = plt.subplots(figsize=(6.5, 4), constrained_layout=True)
    for label, (x, y) in series.items():
        y = np.asarray(y, dtype=float)
        ax.plot(x, np.where(np.isfinite(y), np.maximum(y, 1e-17), np.nan), marker="o", ms=3, label=label)
    ax.set_yscale("log")
    if logx:
        ax.set_xscale("log")
    ax.set_xlabel(xlabel)
    ax.set_ylabel(ylabel)
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8)
    ax.set_title(title)
    return save(fig, path)


def figure_path(out: str, name: str) -> str:
    return os.path.join(out, f"{name}.png")
