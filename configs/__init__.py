"""The shipped configuration files (scanner hardware, protocols, phantoms, backends,
registration settings), as package data: ``importlib.resources.files("configs")`` finds them in
a checkout and in an installed wheel alike."""
