"""The example notebook (docs/notebooks/quickstart.ipynb) runs in a real Jupyter kernel
(nbclient + ipykernel): ``mi_amr.show`` leaves an inline PNG of the size asked, and the
explorer ``mi_amr.explore`` shows answers HTTP at the URL of its iframe while the kernel runs."""

import base64
import io
import json
import re
import urllib.request
from pathlib import Path

import numpy as np
import pytest

nbformat = pytest.importorskip("nbformat")
nbclient = pytest.importorskip("nbclient")
pytest.importorskip("ipykernel")

NOTEBOOK = Path(__file__).resolve().parents[1] / "docs" / "notebooks" / "quickstart.ipynb"


def outputs_of(cell, mime):
    return [o["data"][mime] for o in cell.get("outputs", [])
            if o.get("output_type") in ("display_data", "execute_result") and mime in
            o.get("data", {})]


def png_pixels(data: str) -> np.ndarray:
    import imageio.v3 as iio

    return np.asarray(iio.imread(io.BytesIO(base64.b64decode(data)), extension=".png"))


def get(url: str):
    with urllib.request.urlopen(url, timeout=60) as reply:
        return reply.status, reply.read()


def test01_the_quickstart_notebook_runs_and_shows_an_image_and_the_explorer(tmp_path):
    nb = nbformat.read(NOTEBOOK, as_version=4)
    client = nbclient.NotebookClient(nb, timeout=900, kernel_name="python3",
                                     resources={"metadata": {"path": str(tmp_path)}})
    checked = set()
    with client.setup_kernel():
        for index, cell in enumerate(nb.cells):
            client.execute_cell(cell, index)
            if cell.cell_type != "code":
                continue
            errors = [o for o in cell.outputs if o.get("output_type") == "error"]
            assert not errors, f"cell {index}: {errors}"
            if "mi_amr.show(" in cell.source:
                (png,) = outputs_of(cell, "image/png")
                pixels = png_pixels(png)
                assert pixels.shape == (300, 400, 4), pixels.shape
                alpha = pixels[..., 3]
                assert 0 < (alpha > 0).mean() < 0.9, "the sphere covers part of the image"
                checked.add("image")
            if "mi_amr.explore(" in cell.source:
                (html,) = outputs_of(cell, "text/html")
                url = re.search(r'<iframe src="([^"]+)"', html).group(1)
                assert url.startswith("http://127.0.0.1:")
                status, body = get(url)
                assert status == 200 and b"<html" in body.lower()
                status, body = get(url + "api/state")
                state = json.loads(body)
                assert status == 200 and state["state"]["field"] == "f"
                assert state["state"]["isovalues"] == pytest.approx([0.3])   # (float32)
                checked.add("explorer")
    assert checked == {"image", "explorer"}
    # The example's data file was made in the notebook's folder, nowhere else.
    assert (tmp_path / "sphere.npz").is_file()
