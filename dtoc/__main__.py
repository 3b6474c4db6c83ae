from dtoc.cli.main import run

run()
