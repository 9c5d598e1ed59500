import pyarrow as pa

# Every problem found in a program that could not be used (written by `parse`; no rows for a program
# that parsed). A failed program's `programs.message` is the first of them.
SCHEMA = pa.schema([
    pa.field("program_id", pa.string(), nullable=False),
    pa.field("path", pa.string(), nullable=False),       # the program file, relative to the workflow
    pa.field("line", pa.int32(), nullable=False),        # 1-based line of the file
    pa.field("column", pa.int32()),                      # 1-based byte column; null: the whole block
    pa.field("message", pa.string(), nullable=False),    # what was found and why it cannot be used
])
