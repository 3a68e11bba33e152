from hdrplenoxels.cli import main

main()
