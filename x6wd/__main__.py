import sys

from x6wd.cli import main

sys.exit(main())
