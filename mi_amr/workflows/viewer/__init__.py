"""``python -m mi_amr view SCENE.xml``: an interactive explorer in the browser.

The page changes the isovalues (with the field's histogram behind the slider), the method,
reconstruction, translucent layers (how they are sampled), step and mode, the colour field,
map and range, the camera (drag to orbit, shift-drag to pan, wheel to zoom), the light and
shadows, and saves images, scenes and movie keyframes. Every change that keeps the kernels'
structure is an ``mi.traverse`` update in the same process, compiling nothing.

* :mod:`.state` -- the view's state and how each control maps to ``mi.traverse``
* :mod:`.controls` -- the page's requests checked and turned into states
* :mod:`.sceneio` -- the state written as a Mitsuba scene file
* :mod:`.paths` -- which files the page may open and where it may write
* :mod:`.tiles` -- saved images of any size rendered in tiles of one film size
* :mod:`.worker` -- the render thread (newest request wins, progressive refinement)
* :mod:`.hub` -- the shared state, the connected pages and the file actions
* :mod:`.server` -- the FastAPI app and ``serve()``
* ``static/`` -- the page
"""

from __future__ import annotations


def serve(scene, **options) -> None:
    """Serve the viewer of ``scene`` (see :func:`mi_amr.workflows.viewer.server.serve`)."""
    from mi_amr.workflows.viewer.server import serve as _serve

    _serve(scene, **options)
