"""`python -m boxjax ...` is the `boxjax` command."""

import sys

from boxjax.cli import main

sys.exit(main())
