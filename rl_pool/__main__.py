import sys

from rl_pool.commands.cli import main

sys.exit(main())
