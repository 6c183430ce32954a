from kbbatch.cli import main

main()
