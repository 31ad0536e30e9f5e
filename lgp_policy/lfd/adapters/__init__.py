"""lfd/adapters"""
