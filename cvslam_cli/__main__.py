from cvslam_cli.cli import main

main()
