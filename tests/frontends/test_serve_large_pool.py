"""A 100,000-row items.csv: read and validated (a bad cell named by its row), with and without an
image column; the summary plot of a large pool draws a bounded subset that keeps what matters."""

import io

import pytest
import torch

from torchpref.data.features import FeaturesError, read_features_csv
from torchpref.frontends.serve import summary
from torchpref.frontends.serve.items import items_from_csv
from torchpref.frontends.serve.plot_worker import draw_utility

N = 100_000


def _write(path, X, picture=None):
    with open(path, "w") as fh:
        fh.write("id,a,b,c,d" + (",picture" if picture else "") + "\n")
        for i, r in enumerate(X.tolist()):
            cells = [f"item{i}"] + [repr(v) for v in r]
            fh.write(",".join(cells) + (f",{picture(i)}" if picture else "") + "\n")


@pytest.fixture(scope="module")
def pool():
    return torch.rand(N, 4, generator=torch.Generator().manual_seed(0), dtype=torch.float64)


def test_a_100k_row_csv_reads_and_a_bad_cell_is_named(tmp_path, pool):
    _write(tmp_path / "items.csv", pool)
    X, names, labels = read_features_csv(tmp_path / "items.csv")
    assert X.shape == (N, 4) and torch.equal(X, pool) and names == ["a", "b", "c", "d"] and labels[-1] == f"item{N - 1}"
    with open(tmp_path / "items.csv", "a") as fh:  # one more row, with a cell that is not a number
        fh.write("last,0.5,0.5,n/a,0.5\n")
    with pytest.raises(FeaturesError, match=rf"row {N + 2}, column 'c': 'n/a' is not a finite number"):
        read_features_csv(tmp_path / "items.csv")


@pytest.mark.slow
def test_a_100k_row_csv_with_an_image_column_reads(tmp_path, pool):
    (tmp_path / "img").mkdir()
    png = b"\x89PNG\r\n\x1a\n" + b"\0" * 16
    for k in range(10):
        (tmp_path / "img" / f"{k}.png").write_bytes(png)
    _write(tmp_path / "items.csv", pool, picture=lambda i: f"img/{i % 10}.png")
    items = items_from_csv(tmp_path / "items.csv", image_column="picture")
    assert len(items) == N and torch.equal(items.X, pool) and items.has_pictures
    assert items.picture(N - 1) == (png, "image/png")


def test_a_large_pools_plot_draws_a_bounded_subset_keeping_the_answered_and_the_best():
    n = 3 * summary.PLOT_MAX_POINTS
    mean = torch.linspace(0, 1, n).flip(0)  # row 0 the best
    seen = [7, n - 1, n // 2 + 3]
    rows = summary.plotted_rows(n, seen, mean)
    assert rows.numel() <= summary.PLOT_MAX_POINTS and rows.unique().numel() == rows.numel()
    kept = set(rows.tolist())
    assert set(seen) <= kept and set(range(summary.PLOT_TOP)) <= kept and max(kept) == n - 1
    assert torch.equal(summary.plotted_rows(100, seen[:1], mean[:100]), torch.arange(100))  # a small pool: all
    png = draw_utility(
        {"step": 3, "xs": [0.1, 0.5, 0.9], "ys": [0.2, 0.4, 0.6], "mean": [0.0, 1.0, 0.5], "std": [1.0] * 3,
         "seen": [1], "best": 1, "xlabel": "a", "ylabel": "b", "of": n}
    )  # fmt: skip
    assert png.startswith(b"\x89PNG") and len(io.BytesIO(png).getvalue()) > 1000


@pytest.mark.slow
def test_the_summary_data_of_a_session_over_a_large_pool(pool):
    import torchpref
    from torchpref.frontends.serve.items import ServeItems

    X = pool[:20_000]
    items = ServeItems(X, ["a", "b", "c", "d"])
    s = torchpref.PreferenceSession(X)
    for _ in range(2):
        q = s.ask()
        s.tell(q, 4 if q.kind == "rating" else 0)
    data = summary.utility_data(items, s, 0, 1)
    assert len(data["xs"]) == len(data["mean"]) <= summary.PLOT_MAX_POINTS and data["of"] == 20_000
    best = int(s.predict(X)[0].argmax())
    assert (data["xs"][data["best"]], data["ys"][data["best"]]) == (float(X[best, 0]), float(X[best, 1]))
    answered = {i for r in s.history for i in r.pool_indices}
    assert {(data["xs"][k], data["ys"][k]) for k in data["seen"]} == {
        (float(X[i, 0]), float(X[i, 1])) for i in answered
    }
