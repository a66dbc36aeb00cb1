from services.env_worker.service import main

main()
