# syntax=docker/dockerfile:1
# Two images from one file (docker-compose.yml picks them with `target:`):
#   emulator: the FastAPI emulator service; ONNX Runtime only, no PyTorch (it never imports torch).
#   trainer:  the `neuro` command (train / eval / bench), with the CPU build of PyTorch.
# Pinned versions come from pyproject.toml, so the images and `make install` agree.

FROM python:3.11-slim AS base
ENV PYTHONDONTWRITEBYTECODE=1 PYTHONUNBUFFERED=1 PIP_NO_CACHE_DIR=1 PIP_DISABLE_PIP_VERSION_CHECK=1
WORKDIR /app
COPY pyproject.toml README.md ./

FROM base AS emulator
# Every pinned runtime dependency except the training-only ones (torch, onnx, tqdm, matplotlib).
RUN python -c "import tomllib; deps = tomllib.load(open('pyproject.toml', 'rb'))['project']['dependencies']; \
print('\n'.join(d for d in deps if d.split('==')[0].split('[')[0] not in {'torch', 'onnx', 'tqdm', 'matplotlib'}))" \
    > /tmp/requirements.txt \
 && pip install -r /tmp/requirements.txt
COPY neuroanimator ./neuroanimator
COPY services ./services
RUN pip install --no-deps . && useradd --create-home --uid 10001 neuro
USER neuro
ENV HOST=0.0.0.0 PORT=8000 ARTIFACTS_DIR=/artifacts
EXPOSE 8000
HEALTHCHECK --interval=10s --timeout=3s \
    CMD python -c "import urllib.request; urllib.request.urlopen('http://127.0.0.1:8000/healthz', timeout=2)"
CMD ["python", "-m", "services.emulator"]

FROM base AS trainer
RUN pip install torch==2.13.0 --index-url https://download.pytorch.org/whl/cpu
COPY neuroanimator ./neuroanimator
COPY services ./services
RUN pip install .
ENTRYPOINT ["neuro"]
CMD ["models"]
