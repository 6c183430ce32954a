from kbbatch.entry import main

main()
