from elastocal.cli import main

raise SystemExit(main())
