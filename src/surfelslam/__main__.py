from surfelslam.cli import main

main()
