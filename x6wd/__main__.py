import sys

from x6wd.app.cli import main

sys.exit(main())
