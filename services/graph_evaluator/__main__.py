from services.graph_evaluator.service import main

main()
