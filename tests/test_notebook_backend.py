import nbformat
from _kernel import NoHeartbeatClient


def test_a_plot_call_leaves_the_notebooks_inline_backend(tmp_path):
    """In a notebook kernel with ``%matplotlib inline``, gyrojax drawing a figure (shown, and
    saved to a file) leaves the inline backend in place, and a figure the user draws after it
    still shows inline (before, the plots switched the backend to Agg and later figures
    vanished)."""
    png = tmp_path / "allan.png"
    cells = [
        "%matplotlib inline\nimport matplotlib\nBACKEND = matplotlib.get_backend()\nprint(BACKEND)",
        "import numpy as np\nfrom gyrojax.analysis.spectral import allan_deviation\n"
        "from gyrojax.plots import plot_allan\n"
        "ad = allan_deviation(np.random.default_rng(0).normal(size=20000) * 1e-5, 100.0)\n"
        f"plot_allan(ad, path={str(png)!r})\nplot_allan(ad)\n"
        "assert matplotlib.get_backend() == BACKEND, matplotlib.get_backend()",
        "import matplotlib.pyplot as plt\nplt.plot([0.0, 1.0])\nplt.show()",
    ]
    nb = nbformat.v4.new_notebook(cells=[nbformat.v4.new_code_cell(c) for c in cells])
    NoHeartbeatClient(nb, timeout=300, kernel_name="python3",
                       resources={"metadata": {"path": str(tmp_path)}}).execute()
    outs = [c.get("outputs", []) for c in nb.cells]
    assert not [o for cell in outs for o in cell if o.get("output_type") == "error"]
    assert "inline" in outs[0][0]["text"]
    assert png.read_bytes()[:4] == b"\x89PNG"
    assert any("image/png" in o.get("data", {}) for o in outs[2])
