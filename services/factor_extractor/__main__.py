from services.factor_extractor.service import main

main()
