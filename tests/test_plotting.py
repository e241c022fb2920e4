"""Plotting draws without pyplot: the user's matplotlib backend is never changed."""

import subprocess
import sys


def test_plotting_leaves_the_backend_alone(tmp_path):
    code = (
        "import matplotlib, numpy as np\n"
        "matplotlib.use('svg')\n"
        "from wss_nlp import cli, plotting\n"
        "fig = plotting.figure_band_check(np.linspace(0, 6, 10), np.ones(10), np.ones(10), 5)\n"
        f"plotting.save_figure(fig, {str(tmp_path / 'band.png')!r})\n"
        "print(matplotlib.get_backend())\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "svg"
    assert (tmp_path / "band.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
