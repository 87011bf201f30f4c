"""``python -m colmap_pvs.cli``."""

from colmap_pvs.cli.main import main

raise SystemExit(main())
