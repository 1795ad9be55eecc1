"""Print the commands of the README's "Quick start" code block, one a line.

CI runs exactly these, so the README's set-up and CI cannot drift apart.
"""

import re
import sys
from pathlib import Path

text = Path(sys.argv[1]).read_text()
section = text.split("## Quick start", 1)[1]
block = re.search(r"```bash\n(.*?)```", section, re.S).group(1)
for line in block.splitlines():
    if line.strip() and not line.lstrip().startswith("#"):
        print(line.strip())
