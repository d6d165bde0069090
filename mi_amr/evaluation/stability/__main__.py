"""``python -m mi_amr.evaluation.stability``: see :func:`mi_amr.evaluation.stability.main`."""

from mi_amr.evaluation.stability.suite import main

raise SystemExit(main())
