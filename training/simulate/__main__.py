"""``python -m training.simulate``: the physics reference's command line (``training.simulate.cli``)."""
from training.simulate.cli import main

if __name__ == "__main__":
    main()
