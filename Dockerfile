# Vision Lab, CPU only: the landing page and REST API on 8000, the 3D viewer on 8080.
#   docker build -t vision-lab . && docker run --rm --cap-add SYS_ADMIN --security-opt apparmor=unconfined \
#       --security-opt seccomp=unconfined -p 8000:8000 -p 8080:8080 vision-lab
# The three flags let bubblewrap create the grading sandbox's namespaces (docs/sandbox.md); without
# them every module still works and submissions are refused with a 503 naming this fix.
FROM python:3.11-slim

# bubblewrap: each submission runs in its own namespaces; setpriv (util-linux) drops it to its own user.
RUN apt-get update && apt-get install -y --no-install-recommends bubblewrap util-linux \
    && rm -rf /var/lib/apt/lists/*

ENV PYTHONDONTWRITEBYTECODE=1 \
    PYTHONUNBUFFERED=1 \
    PIP_NO_CACHE_DIR=1 \
    PIP_DISABLE_PIP_VERSION_CHECK=1

# The CPU build of the pinned PyTorch first, so that installing the project keeps it
# (torch==2.13.0 in pyproject.toml is satisfied by 2.13.0+cpu) instead of pulling a CUDA build.
RUN python -m pip install --index-url https://download.pytorch.org/whl/cpu torch==2.13.0

WORKDIR /app
COPY . .
# Editable, so the lab finds its landing page and lessons beside the package, as in a checkout.
RUN python -m pip install -e .

EXPOSE 8000 8080
HEALTHCHECK --interval=30s --timeout=5s --start-period=30s \
    CMD python -c "import urllib.request; urllib.request.urlopen('http://127.0.0.1:8000/api/health', timeout=4)"
CMD ["vision-lab", "serve", "--host", "0.0.0.0"]
