import sys

from mi_amr.cli import main

sys.exit(main())
