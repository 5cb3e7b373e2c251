"""stages/offline"""
