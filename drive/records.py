"""The MCAP library as the layers above the drive layer see it: its record types, its record-by-record stream
reader, its reader and its writer, named here once so that only the drive layer depends on the library
(tests/test_imports.py checks that no other module imports ``mcap``).

``acquire.recovery`` walks a file cut short record by record; ``tools.filter`` copies schemas and channels;
``tools.foxglove_live`` reads a summary and messages in log-time order; ``tools.dev`` writes the layouts other
writers make, with the library's own writer."""
from mcap.opcode import Opcode
from mcap.reader import make_reader
from mcap.records import Channel, Chunk, DataEnd, Footer, Message, Metadata, Schema
from mcap.stream_reader import StreamReader
from mcap.writer import CompressionType, IndexType, Writer

__all__ = ["Channel", "Chunk", "CompressionType", "DataEnd", "Footer", "IndexType", "Message", "Metadata", "Opcode",
           "Schema", "StreamReader", "Writer", "make_reader"]
