import sys

from mi_amr.cli import main

if __name__ == "__main__":      # (Dask's worker processes import this module too)
    sys.exit(main(prog="python -m mi_amr"))
