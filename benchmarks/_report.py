"""Shared output of the benchmark scripts: a table printed as it fills, and a finished plot."""


class Table(list):
    """Rows of strings; each row is printed when appended, the aligned table by `print_all`."""

    def append(self, row):
        super().append(tuple(row))
        print("  ".join(row), flush=True)

    def print_all(self):
        width = [max(len(r[i]) if i < len(r) else 0 for r in self) for i in range(max(map(len, self)))]
        print("\n" + "\n".join("  ".join(c.ljust(w) for c, w in zip(r, width)) for r in self))


def finish_plot(fig, ax, path, xlabel: str, ylabel: str, title: str, grid: bool = True, legend: dict | None = None):
    """Label, legend (`legend`: `ax.legend`'s keywords) and save a figure (PNG, 120 dpi)."""
    ax.set_xlabel(xlabel)
    ax.set_ylabel(ylabel)
    ax.set_title(title)
    if grid:
        ax.grid(True, which="both", alpha=0.3)
    ax.legend(**(legend or {}))
    fig.tight_layout()
    fig.savefig(path, dpi=120)
