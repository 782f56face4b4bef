import sys

from fullview.cli import main

sys.exit(main())
