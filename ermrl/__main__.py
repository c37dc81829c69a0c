from ermrl.cli import main

raise SystemExit(main())
