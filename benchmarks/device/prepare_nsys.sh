#!/usr/bin/env bash
# Here (not on the device): the shared libraries Nsight Systems' trace importer needs on the GPU machine.
# The device has only the nsys bundled with Nsight Compute; `nsys profile` writes its raw .qdstrm but the
# importer that turns it into a report (QdstrmImporter) fails there: "libdw.so.1: cannot open shared object
# file". This puts libdw, libelf, libbz2 and liblzma (Debian packages, no root needed) in .gpu/nsys/lib, with
# a stage script; carry [".gpu/nsys"] and see benchmarks/device/nsys_dataset.sh.
set -e
cd "$(dirname "$0")/../.."
rm -rf .gpu/nsys && mkdir -p .gpu/nsys/lib .gpu/nsys/deb
(cd .gpu/nsys/deb && apt-get download libdw1 libelf1 libbz2-1.0 liblzma5 2>/dev/null)
for f in .gpu/nsys/deb/*.deb; do dpkg-deb -x "$f" .gpu/nsys/x; done
find .gpu/nsys/x -name "*.so*" -exec cp -L {} .gpu/nsys/lib/ \;   # real files: a carry may drop links
rm -rf .gpu/nsys/x .gpu/nsys/deb
cat > .gpu/nsys/stage.sh <<'EOS'
#!/usr/bin/env bash
mkdir -p /tmp/nsyslib && cp "$(dirname "$0")"/lib/* /tmp/nsyslib/ && echo "nsys libraries in /tmp/nsyslib"
EOS
ls .gpu/nsys/lib
