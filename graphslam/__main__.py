from graphslam.cli import main

main()
