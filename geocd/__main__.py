from geocd.cli import main

main()
