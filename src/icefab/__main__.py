import sys

from icefab.cli import main

sys.exit(main())
