from nerfbake.cli import main
import sys
sys.exit(main())
