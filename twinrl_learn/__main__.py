from twinrl_learn.cli import main

main()
