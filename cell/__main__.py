import sys

from cell.cli import main

sys.exit(main())
