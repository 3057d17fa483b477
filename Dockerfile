# One image for every KM-ViPE service; docker-compose picks the service with `kmvipe service NAME`.
FROM python:3.11-slim
# libtcmalloc-minimal4: the allocator ba runs on (services/common/allocator.py; docs/BENCHMARKS.md, forty-seventh session)
RUN apt-get update && apt-get install -y --no-install-recommends libgl1 libglib2.0-0 libtcmalloc-minimal4 \
    && rm -rf /var/lib/apt/lists/*
WORKDIR /app
COPY pyproject.toml README.md ./
COPY scripts scripts
COPY services services
# CPU PyTorch (the install script never pulls CUDA wheels on a machine without nvidia-smi); a regular, not
# editable, install: the image runs the package copied into /opt/venv. CI installs the same way
# (.ci/run, tests/test_production_install.py).
RUN VENV=/opt/venv EXTRAS=models EDITABLE=0 ./scripts/install.sh
ENV PATH=/opt/venv/bin:$PATH \
    KMVIPE_MODELS_DIR=/models \
    HF_HOME=/models/huggingface
ENTRYPOINT ["kmvipe"]
CMD ["--help"]
