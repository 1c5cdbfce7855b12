"""`benchmarks/stiff_fit.py --quick` runs end to end: Robertson from its first start, torchql and
scipy reaching the same optimum (no timing assertions)."""

import pytest

pytest.importorskip("scipy")


@pytest.mark.slow
def test_stiff_fit_quick_fits_robertson_to_scipys_optimum(tmp_path, run_script):
    run = run_script("benchmarks/stiff_fit.py", "--quick", "--out", str(tmp_path), timeout=600)
    assert run.returncode == 0, run.stderr[-2000:]
    # the table is printed after each problem and once more at the end: its distinct rows
    rows = list(dict.fromkeys(line for line in run.stdout.splitlines() if line.startswith("| Robertson")))
    assert len(rows) == 1, run.stdout[-2000:]
    cells = [cell.strip() for cell in rows[0].strip().strip("|").split("|")]
    assert cells[4].startswith("CONVERGED"), rows[0]
    assert cells[6] == "yes" and cells[10] == "yes", rows[0]  # both within 1e-6 of the best SSE
    assert not (tmp_path / "stiff_fit.md").exists()  # a quick run leaves the recorded table alone


def test_the_scipy_peers_hires_is_the_model_at_other_rates():
    """The NumPy right-hand side and Jacobian that scipy fits HIRES with (``stiff_simulate.hires_numpy``)
    equal torchql's model at rates other than the defaults, so both fit the same problem."""
    import sys
    from pathlib import Path

    import numpy as np
    import torch
    from torch.func import jacrev

    from torchql.models import HIRES

    folder = str(Path(__file__).resolve().parents[2] / "benchmarks")
    sys.path.insert(0, folder)
    try:
        from stiff_simulate import hires_numpy
    finally:
        sys.path.remove(folder)
    rates = {"k1": 2.0, "k7": 350.0, "k8": 0.55}
    f, jac = hires_numpy(rates)
    model = HIRES(**rates)
    y = torch.rand(8, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    t = torch.tensor(1.0, dtype=torch.float64)
    np.testing.assert_allclose(f(1.0, y.numpy()), model(t, y).numpy(), rtol=1e-14, atol=1e-16)
    np.testing.assert_allclose(jac(1.0, y.numpy()), jacrev(model, argnums=1)(t, y).numpy(), rtol=1e-14, atol=1e-16)
