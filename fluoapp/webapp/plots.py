"""Small matplotlib figures for the app, as PNG data URLs (no files, no display)."""

from __future__ import annotations

import base64
import io

__all__ = ["png_data_url", "bar_chart"]


def png_data_url(fig):
    """Render a matplotlib figure to a ``data:image/png;base64,...`` URL and close it."""
    import matplotlib.pyplot as plt

    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=110, bbox_inches="tight")
    plt.close(fig)
    return "data:image/png;base64," + base64.b64encode(buf.getvalue()).decode("ascii")


def bar_chart(labels, values, ylabel, title, hline=None, hline_label=None):
    """A readable bar chart (one bar per label) as a data URL."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(4.2, 2.6))
    ax.bar(range(len(values)), values, color="#3b7dd8")
    ax.set_xticks(range(len(values)))
    ax.set_xticklabels(labels, rotation=60, ha="right", fontsize=7)
    ax.set_ylabel(ylabel)
    ax.set_title(title, fontsize=10)
    if hline is not None:
        ax.axhline(hline, color="#d62728", lw=1, ls="--", label=hline_label)
        if hline_label:
            ax.legend(fontsize=7)
    ax.grid(axis="y", alpha=0.3)
    return png_data_url(fig)
