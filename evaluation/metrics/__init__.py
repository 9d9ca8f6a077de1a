"""(filled in by the restructuring of issue #18)"""
