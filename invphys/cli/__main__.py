from invphys.cli import main

main()
