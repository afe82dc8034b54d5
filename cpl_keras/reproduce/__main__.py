"""``python -m cpl_keras.reproduce``: the reproduction's command line."""

if __name__ == "__main__":  # the command line: cpl_keras/commands/reproduce.py
    import runpy

    runpy.run_module("cpl_keras.commands.reproduce", run_name="__main__")
