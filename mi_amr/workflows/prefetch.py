"""Preparing the next data file of a time series while this one renders: the viewer stepping
through ``--files`` (:mod:`mi_amr.workflows.viewer.series`) and a movie's frames rendered in one
process (:mod:`mi_amr.workflows.movie.frames`) both read, derive and build step ``k + 1`` in a
background thread while step ``k``'s frame renders. On the CPU the two share the cores; the
frame's kernels run outside Python's lock, so the preparation's NumPy work and the render
overlap.
"""

from __future__ import annotations

import threading

from mi_amr.errors import AMRError, print_traceback


class Prefetcher:
    """Prepares one data file at a time in a background thread, into the integrator's
    :class:`~mi_amr.kernels.prepared.Preparations` (the render thread then finds it there). The render thread
    calls :meth:`wait` before it loads anything itself, so the two never prepare at once."""

    def __init__(self):
        self._thread = None
        self.path = None
        self._args = None               # what was prepared last (file, fields, backend)

    def start(self, integrator, path) -> None:
        """Prepare ``path`` for ``integrator`` (its field, colour field, backend), unless it is
        prepared (or being prepared) for it already."""
        from mi_amr.kernels.prepared import LoadOptions

        opt = integrator.opt
        basis = opt.reconstruction == "basis"
        args = (integrator.preparations, str(path), opt.field, opt.color_field,
                LoadOptions(opt.leaf_cells, opt.allow_nonfinite, keep_fields=not basis),
                integrator.m, basis)
        if args == self._args:
            return
        self.wait()
        self.path, self._args = str(path), args
        self._thread = threading.Thread(target=self._prepare, args=args,
                                        name="mi_amr-prefetch", daemon=True)
        self._thread.start()

    def _prepare(self, preparations, path, field, color_field, how, m, basis) -> None:
        """``how``: the :class:`~mi_amr.kernels.prepared.LoadOptions` of the integrator's."""
        import drjit as dr

        try:
            preparations.prepare(path, field, color_field, m=m, how=how).search_ready(basis)
            dr.sync_thread()
        except AMRError:                # a bad file: the step loads it itself and says why
            pass
        except Exception:               # a bug: print it; the step loads the file itself
            print_traceback()

    def wait(self) -> None:
        """Until the preparation under way (if any) is done."""
        if self._thread is not None:
            self._thread.join()
            self._thread = None

    def finished(self):
        """The file last prepared when its preparation is done (None while it runs, or when
        none was started)."""
        thread = self._thread
        return self.path if thread is None or not thread.is_alive() else None
