"""aerovis_train: training, evaluation and search of the event keypoint networks (torch).

It imports the runtime's event and MCTS code (:mod:`aerovis_slam`) so that training and
deployment preprocess identically. Importing this package itself stays light (no torch), so
command-line tools such as ``aerovis-bench mcts`` start fast.
"""
